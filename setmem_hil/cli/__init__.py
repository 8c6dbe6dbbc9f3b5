"""The setmem-hil command line (one module per command in setmem_hil.cli.commands)."""

