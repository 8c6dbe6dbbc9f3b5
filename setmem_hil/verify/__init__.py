"""The closed-loop verification (issue 45): a second plan on the run engine that loads the
compensator into a real-time target, engages it in steps, measures the closed loop and checks
every point against the box's prediction (``setmem-hil verify``; docs/real-time-target.md)."""
