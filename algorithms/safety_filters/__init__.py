"""Safety filters (TEMPORARY stand-in; the ``cbf`` branch owns this file)."""

from scg_algorithms.safety_filters.base import FILTERS, FilterInfo, JaxFilter, SafetyFilter

__all__ = ["FILTERS", "FilterInfo", "JaxFilter", "SafetyFilter"]
