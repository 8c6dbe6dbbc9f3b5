"""The campaign: Algorithm 5.1 (runner), its subscribers (observers) and the run application layer (session)."""

from setmem_hil.campaign.runner import CampaignSummary, run_campaign

__all__ = ["CampaignSummary", "run_campaign"]
