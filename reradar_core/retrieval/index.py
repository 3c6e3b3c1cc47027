"""Retrieval: nearest neighbours of a query's global descriptor among a map's keyframes.

``GlobalIndex`` is the FAISS index over a map's global descriptors (inner product on L2-normalised rows =
cosine similarity); ``EuclideanIndex`` is the exact brute-force search the baselines use for descriptors that
are not unit vectors (VLAD, ring keys), where every distance is needed (PR curves).

Exact search (``IndexFlatIP``) up to ``IndexConfig.exact_max_size`` keyframes, IVF-Flat above (k-means
lists, ``nprobe`` of them scanned per query: ~0.2 ms per query on 10^5 keyframes with the exact top-1 in our
benchmark, and it trains in seconds where HNSW takes minutes to build); HNSW is available on request. Descriptor distance reported to users is the Euclidean
distance between unit vectors, ``sqrt(2 - 2 cos)`` in [0, 2].
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from reradar_core.errors import ConfigError

if TYPE_CHECKING:
    import faiss

__all__ = ["IndexConfig", "GlobalIndex", "EuclideanIndex", "similarity_to_distance"]

logger = logging.getLogger(__name__)

_KINDS = ("auto", "flat", "hnsw", "ivf")


@dataclass(frozen=True)
class IndexConfig:
    """How to index global descriptors.

    Attributes:
        kind: ``auto`` (flat up to ``exact_max_size``, else IVF), ``flat`` (exact), ``hnsw`` or ``ivf``.
        exact_max_size: largest map searched exactly by ``auto``. Flat search costs O(N*D) per query;
            at D=256 a 20,000-keyframe scan takes ~1 ms on one core.
        hnsw_m: HNSW graph degree.
        hnsw_ef_construction, hnsw_ef_search: HNSW build / search beam widths (recall vs speed).
        ivf_nlist, ivf_nprobe: IVF lists and lists probed per query.
        num_threads: FAISS OpenMP threads (1: one request at a time should not fight the model for cores).
    """

    kind: str = "auto"
    exact_max_size: int = 20_000
    hnsw_m: int = 32
    hnsw_ef_construction: int = 80
    hnsw_ef_search: int = 64
    ivf_nlist: int = 1024
    ivf_nprobe: int = 16
    num_threads: int = 1

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ConfigError(f"unknown index kind {self.kind!r}; choose one of {_KINDS}")
        if self.exact_max_size < 0 or self.hnsw_m < 4 or self.ivf_nlist < 1 or self.num_threads < 1:
            raise ConfigError(f"invalid index configuration {self}")


def similarity_to_distance(sim: np.ndarray) -> np.ndarray:
    """Euclidean distance between unit vectors from their inner product: ``sqrt(max(0, 2 - 2 s))``."""
    return np.sqrt(np.maximum(0.0, 2.0 - 2.0 * np.asarray(sim, dtype=np.float64)))


class GlobalIndex:
    """Nearest-neighbour search over (N, D) float32 L2-normalised descriptors.

    Attributes:
        kind: the index type actually built (``flat``, ``hnsw`` or ``ivf``).
        size: N; dim: D.
    """

    def __init__(self, descriptors: np.ndarray, config: IndexConfig = IndexConfig()) -> None:
        import faiss  # here, not at import: the vehicle client never loads it

        x = np.ascontiguousarray(np.asarray(descriptors, dtype=np.float32))
        if x.ndim != 2:
            raise ConfigError(f"descriptors must be (N, D), got shape {x.shape}")
        self.size, self.dim = x.shape
        self.config = config
        faiss.omp_set_num_threads(config.num_threads)
        kind = config.kind
        if kind == "auto":
            kind = "flat" if self.size <= config.exact_max_size else "ivf"
        if kind == "ivf" and self.size < 39 * min(config.ivf_nlist, max(1, self.size // 39)):
            kind = "flat"  # too few points to train IVF lists
        self.kind = kind
        if kind == "flat":
            index: faiss.Index = faiss.IndexFlatIP(self.dim)
        elif kind == "hnsw":
            index = faiss.IndexHNSWFlat(self.dim, config.hnsw_m, faiss.METRIC_INNER_PRODUCT)
            index.hnsw.efConstruction = config.hnsw_ef_construction
            index.hnsw.efSearch = config.hnsw_ef_search
        else:
            nlist = min(config.ivf_nlist, max(1, self.size // 39))
            quantizer = faiss.IndexFlatIP(self.dim)
            index = faiss.IndexIVFFlat(quantizer, self.dim, nlist, faiss.METRIC_INNER_PRODUCT)
            # k-means on a fixed-seed sample: deterministic lists, bounded training time
            sample = x if self.size <= 256 * nlist else x[np.random.default_rng(0).choice(self.size, 256 * nlist, replace=False)]
            index.cp.seed = 0
            index.train(sample)
            index.nprobe = min(config.ivf_nprobe, nlist)
            index.make_direct_map()  # ``vector(i)`` (8 bytes per keyframe)
            self._quantizer = quantizer  # keep alive: FAISS does not own it
        if self.size:
            index.add(x)
        if kind == "ivf" and self.size:
            # the inverted lists grew one vector at a time (vector capacity doubling leaves ~25 % of their
            # memory unused on average); a serialise round trip stores every list at its exact size
            nprobe = min(config.ivf_nprobe, index.nlist)  # type: ignore[attr-defined]
            index = faiss.deserialize_index(faiss.serialize_index(index))  # owns its own quantizer
            index.nprobe = nprobe  # type: ignore[attr-defined]
            del self._quantizer
        self._index = index
        logger.debug("built %s index over %d x %d descriptors", kind, self.size, self.dim)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` neighbours of each query.

        Args:
            queries: (D,) or (Q, D) float32 L2-normalised.
            k: neighbours wanted (clipped to N).

        Returns:
            indices (Q, k') int64 keyframe ids, best first; similarities (Q, k') float32 inner products.
            k' = min(k, N); missing neighbours (HNSW/IVF) are dropped from the end as -1 ids.
        """
        q = np.ascontiguousarray(np.asarray(queries, dtype=np.float32))
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ConfigError(f"query descriptors must have {self.dim} columns, got shape {q.shape}")
        k = min(int(k), self.size)
        if k <= 0:
            return np.zeros((q.shape[0], 0), np.int64), np.zeros((q.shape[0], 0), np.float32)
        sims, idx = self._index.search(q, k)
        return idx.astype(np.int64), sims.astype(np.float32)

    def vector(self, i: int) -> np.ndarray:
        """(D,) float32 indexed descriptor ``i`` (exact for every index kind)."""
        return np.asarray(self._index.reconstruct(int(i)), np.float32)

    def distances(self, query: np.ndarray) -> np.ndarray:
        """(N,) float64 Euclidean distances between the unit query (D,) and every indexed descriptor
        (``similarity_to_distance`` of the inner products; exact for ``flat``, missing rows = 2 otherwise)."""
        idx, sims = self.search(query, self.size)
        out = np.full(self.size, 2.0)
        ok = idx[0] >= 0
        out[idx[0][ok]] = similarity_to_distance(sims[0][ok])
        return out

    @property
    def memory_bytes(self) -> int:
        """Approximate resident bytes of the index (vectors plus graph/list overhead)."""
        base = self.size * self.dim * 4
        if self.kind == "hnsw":
            base += self.size * self.config.hnsw_m * 2 * 4
        elif self.kind == "ivf":
            base += self.size * 8
        return int(base)


class EuclideanIndex:
    """Stacked (N, D) float32 descriptors with cached squared norms: exact Euclidean distances to every row by
    one mat-vec (no per-query (N, D) temporaries, which dominate the search time of long VLAD descriptors).
    For descriptors that are not unit vectors; ``GlobalIndex`` serves the unit global descriptors of maps."""

    def __init__(self, descs: Sequence[np.ndarray] | np.ndarray) -> None:
        self.matrix = np.ascontiguousarray(np.stack([np.asarray(d, np.float32).reshape(-1) for d in descs]))
        self.sq_norms = np.einsum("nd,nd->n", self.matrix, self.matrix, dtype=np.float64)

    def __len__(self) -> int:
        return int(self.matrix.shape[0])

    def distances(self, q: np.ndarray) -> np.ndarray:
        """(N,) float64 Euclidean distances to ``q`` (D,)."""
        q = np.asarray(q, np.float32).reshape(-1)
        d2 = self.sq_norms - 2.0 * (self.matrix @ q).astype(np.float64) + float(np.dot(q, q))
        return np.sqrt(np.maximum(d2, 0.0))
