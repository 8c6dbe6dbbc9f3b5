"""The campaign: Algorithm 5.1 as a plan on the run engine, its subscribers and the run's lifecycle.

``run_campaign`` and ``CampaignSummary`` are loaded on first use (the loop's numerics are heavy;
``run --check`` and ``--help`` must not pay for them).
"""

__all__ = ["CampaignSummary", "run_campaign"]


def __getattr__(name: str):
    if name in __all__:
        from setmem_hil.campaign import runner

        return getattr(runner, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
