"""The run layer every plan shares (issue 63 item 6): the run engine (:mod:`.engine`), the run's
directory and its lock (:mod:`.run_directory`), the signals and the rig's safety notes
(:mod:`.rig_safety`), and the one safe exit (:mod:`.safe_exit`). The campaign
(:mod:`setmem_hil.campaign`) and the closed-loop verification (:mod:`setmem_hil.verify`) are plans
on it; neither keeps its own copy of any of these.
"""
