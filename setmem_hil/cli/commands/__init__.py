"""CLI subcommands, one module per command.

Each module defines ``register(subparsers)`` which adds its subparser and sets
``func(args) -> int`` (the exit code). :data:`COMMANDS` names every command with its module and
its one-line help, so ``setmem-hil --help`` lists them without importing any (a command's
module, and what it needs, is imported only when that command runs; issue 46). A test checks
that each module registers the command and the help given here.
"""

COMMANDS: dict[str, tuple[str, str]] = {
    "analyze": ("analyze", "H2 design, mixed-mu robust performance and mu-sensitivities of a model"),
    "calibrate-channels": ("calibrate_channels", "measure the oscilloscope's channel gains (generator on a tee to every channel)"),
    "campaign": ("campaign", "run a procedure's campaign into DIR, with a backend override (scripts)"),
    "controller": ("controller", "export the compensator a run kept (JSON, .mat, second-order sections, C header)"),
    "demo": ("demo", "run the thesis section 6.3.2 campaign on the simulated beam"),
    "discrepancy": ("discrepancy", "find and name what the model lacks, add it, show the gap shrink"),
    "export": ("export", "write a run's measurements, bounds and mu-bar per iteration as CSV"),
    "identify": ("identify", "guaranteed interval bounds of a modal model from frequency data"),
    "identify-matrix": ("identify_matrix", "guaranteed intervals of a structure's FRF matrix (several exciters and sensors, shared poles)"),
    "prior": ("prior", "propose a prior (PRIOR.toml) from a measured FRF"),
    "probe": ("probe", "connect to the procedure's instruments, check identities; outputs stay off"),
    "report": ("report", "write DIR/report.html: figures 6-12, 6-13, 6-14, sample transfer functions, pole-zero patterns, "
               "interval tables"),
    "reprocess": ("reprocess", "recompute every measurement from its raw record and compare with the journal"),
    "run": ("run", "run a campaign from a procedure file (or resume one)"),
    "sweep": ("sweep", "many campaigns (seeds x input-design strategies x designs) on Dask, resumable"),
    "validate": ("validate", "check the compensator a run kept against the truth and plants sampled from the interval box"),
    "verify": ("verify", "load the compensator into a real-time target, engage it in steps and check the closed loop against the box"),
    "view": ("view", "watch a run (going on elsewhere, or finished) in the browser, read-only"),
}
"""command name -> (module in this package, one-line help)."""
