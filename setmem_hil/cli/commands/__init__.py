"""CLI subcommands, one module per command.

Each module defines ``register(subparsers)`` which adds its subparser and sets
``func(args) -> int`` (the exit code). ``setmem_hil.cli.main`` discovers them automatically.
"""
