"""Falsification: the shield driven over a grid of traffic conditions (:mod:`~safelane.running.falsify.grid`)
or by a cross-entropy search for the conditions where it breaks most often
(:mod:`~safelane.running.falsify.search`)."""

from safelane.running.falsify.grid import CampaignSpec, load_campaign_spec, run_campaign
from safelane.running.falsify.search import SearchSpec, load_falsify_spec, run_search

__all__ = ["CampaignSpec", "SearchSpec", "load_campaign_spec", "load_falsify_spec", "run_campaign", "run_search"]
