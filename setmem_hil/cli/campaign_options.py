"""What the commands that run a campaign (``run``, ``campaign``, ``demo``, ``sweep``) share: the
``--design`` option's help and the sentence they say when stopped (kept light: ``--help`` must
not import the numerics)."""

SAFE_STOP = "interrupted; exciter at zero, journal closed"
"""What commands that drive an exciter and write a journal say on Ctrl-C, SIGTERM or Abort."""

DESIGN_HELP = ("override the procedure's [design] method: robust (the compensator tuned to the mixed-mu bound, "
               "the default) or h2 (the thesis's H2 design)")
