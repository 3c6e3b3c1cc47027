"""Retrieval stage: nearest keyframes of a query's global descriptor (FAISS ``GlobalIndex``; exact
``EuclideanIndex`` for the baselines' non-unit descriptors)."""

from reradar_core.retrieval.index import EuclideanIndex, GlobalIndex, IndexConfig, similarity_to_distance

__all__ = ["EuclideanIndex", "GlobalIndex", "IndexConfig", "similarity_to_distance"]
