"""The live view: a local page where the technician watches and steers a campaign.

:class:`setmem_hil.live.server.LiveServer` serves the page and its JSON API on 127.0.0.1 (aiohttp,
server-sent events); :func:`setmem_hil.live.state.journal_state` is the state shown, read from the
journal (so a reloaded page or a second viewer loses nothing); :class:`setmem_hil.live.control.LiveControl`
is the runner's :class:`~setmem_hil.model.experiment.CampaignControl` behind the buttons.
"""
