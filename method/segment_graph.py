"""Scene segment graph: one node per 3D segment, an edge where two segments share a 3D boundary.

File format (one ``.npz``, written atomically)::

    format      str, "selfseg.segment_graph/1"
    labels      N int32   segment of each reconstructed object point, −1 = none; segments 0..S−1
    edges       E×2 int32 segment pairs (i < j) with points within adjacency_radius_m of each other
                (tested on per-segment means of quarter-radius cells)
    centroids   S×3 float64, world metres
    sizes       S int64   point counts
    adjacency_radius_m  float
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from selfseg.fileio import FileFormatError, atomic_write_bytes
from selfseg.method.supervoxels import pack_keys

FORMAT = "selfseg.segment_graph/1"


@dataclass
class SegmentGraph:
    """Segments of one scene's object points and their 3D adjacency (see the module docstring)."""

    labels: np.ndarray
    edges: np.ndarray
    centroids: np.ndarray
    sizes: np.ndarray
    adjacency_radius_m: float = 0.0075

    @property
    def n_segments(self) -> int:
        return len(self.sizes)

    def components(self) -> list[np.ndarray]:
        """Weakly connected components as sorted arrays of segment ids, largest first."""
        S = self.n_segments
        if S == 0:
            return []
        g = coo_matrix((np.ones(len(self.edges)), (self.edges[:, 0], self.edges[:, 1])), shape=(S, S))
        n, comp = connected_components(g, directed=False)
        out = [np.nonzero(comp == c)[0].astype(np.int32) for c in range(n)]
        return sorted(out, key=lambda a: (-len(a), int(a[0])))

    def point_indices(self, s: int) -> np.ndarray:
        """Indices of the points of segment ``s``."""
        if not 0 <= s < self.n_segments:
            raise IndexError(f"segment {s} out of range 0..{self.n_segments - 1}")
        return np.nonzero(self.labels == s)[0]

    def save(self, path: str | Path) -> None:
        buf = io.BytesIO()
        np.savez_compressed(buf, format=np.array(FORMAT), labels=self.labels.astype(np.int32),
                            edges=self.edges.astype(np.int32).reshape(-1, 2),
                            centroids=self.centroids.astype(np.float64), sizes=self.sizes.astype(np.int64),
                            adjacency_radius_m=np.array(self.adjacency_radius_m))
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> "SegmentGraph":
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["format"]) != FORMAT:
                    raise FileFormatError(f"{path}: format {str(z['format'])!r}, expected {FORMAT!r}")
                g = cls(labels=z["labels"], edges=z["edges"], centroids=z["centroids"], sizes=z["sizes"],
                        adjacency_radius_m=float(z["adjacency_radius_m"]))
        except (KeyError, ValueError, OSError) as e:
            raise FileFormatError(f"{path}: not a segment graph file ({e})") from None
        if g.centroids.shape != (g.n_segments, 3) or (len(g.labels) and g.labels.max(initial=-1) >= g.n_segments):
            raise FileFormatError(f"{path}: inconsistent segment graph arrays")
        return g


def build_segment_graph(points: np.ndarray, labels: np.ndarray, adjacency_radius_m: float = 0.0075) -> SegmentGraph:
    """Graph of segments 0..S−1 of ``labels`` (−1 ignored) over N×3 world points (m).

    Two segments are adjacent when a point of one lies within ``adjacency_radius_m`` of a point of the
    other. For speed, each segment's points are first pooled into cells of a quarter radius (their
    mean), so the test is exact up to that cell size.
    """
    points = np.asarray(points, np.float64)
    labels = np.asarray(labels, np.int32)
    if len(points) != len(labels):
        raise ValueError(f"{len(points)} points but {len(labels)} labels")
    S = int(labels.max(initial=-1)) + 1
    sizes = np.bincount(labels[labels >= 0], minlength=S).astype(np.int64)
    if S and (sizes == 0).any():
        raise ValueError(f"labels must be consecutive 0..S-1; empty segments {np.nonzero(sizes == 0)[0][:5].tolist()}")
    idx = np.nonzero(labels >= 0)[0]
    centroids = np.zeros((S, 3))
    np.add.at(centroids, labels[idx], points[idx])
    centroids /= np.maximum(sizes, 1)[:, None]
    pairs = boundary_pairs(points, labels, adjacency_radius_m)
    edges = np.unique(pairs, axis=0).astype(np.int32) if len(pairs) else np.zeros((0, 2), np.int32)
    return SegmentGraph(labels=labels, edges=edges, centroids=centroids, sizes=sizes,
                        adjacency_radius_m=float(adjacency_radius_m))


def boundary_pairs(points: np.ndarray, labels: np.ndarray, adjacency_radius_m: float) -> np.ndarray:
    """P×2 int32 segment pairs (i < j), one row per pair of cell representatives of two segments within
    ``adjacency_radius_m`` (m) of each other: the pairs behind each edge of :func:`build_segment_graph`, whose count
    per edge grows with the length of the two segments' shared boundary. ``labels``: −1 ignored."""
    labels = np.asarray(labels, np.int32)
    idx = np.nonzero(labels >= 0)[0]
    if len(idx) < 2:
        return np.zeros((0, 2), np.int32)
    # one representative (mean) point per segment and cell of a quarter radius keeps dense clouds fast
    points = np.asarray(points, np.float64)
    cell = np.floor(points[idx] / (0.25 * adjacency_radius_m)).astype(np.int64)
    key, lab = pack_keys(cell - cell.min(0)), labels[idx]
    order = np.lexsort((lab, key))
    new = np.r_[True, (np.diff(key[order]) != 0) | (np.diff(lab[order]) != 0)]
    rep = np.empty(len(idx), np.int64)
    rep[order] = np.cumsum(new) - 1
    cnt = np.bincount(rep)
    rep_pts = np.zeros((len(cnt), 3))
    np.add.at(rep_pts, rep, points[idx])
    rep_pts /= cnt[:, None]
    rep_lab = np.zeros(len(cnt), np.int32)
    rep_lab[rep] = lab
    pairs = cKDTree(rep_pts).query_pairs(adjacency_radius_m, output_type="ndarray")
    a, b = rep_lab[pairs[:, 0]], rep_lab[pairs[:, 1]]
    cross = a != b
    return np.stack([np.minimum(a[cross], b[cross]), np.maximum(a[cross], b[cross])], 1).astype(np.int32)
