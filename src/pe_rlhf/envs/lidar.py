"""A 2-D lidar in the ego vehicle's frame: exact ray casting against oriented rectangles.

Output layout and conventions
-----------------------------
``EgoLidar.scan`` returns a float32 array of shape ``(beams,)``. Beam ``i`` points at the
world angle ``ego_heading + 2*pi*i/beams`` (math convention, ``atan2(y, x)``): beam 0
looks straight ahead along the ego heading and indices increase with the angle, so beam
``beams/4`` looks at the ego's +y side (highway-env's lane-index-increasing side). The
lidar is ego-framed on purpose: highway-env's own ``LidarObservation`` bins angles in the
world frame, so the same traffic situation reads differently on curves and roundabouts
depending on where the road happens to point; here the scan depends only on the scene
relative to the ego (rotating the ego and the scene together leaves it unchanged).

Normalisation: each value is the distance from the ego centre to the first hit divided by
``max_range``, in [0, 1]; 1.0 means nothing is hit within range, 0.0 means the ego centre
lies inside an object (every beam starts inside it).

Method: objects (centre, heading, LENGTH along the heading, WIDTH) are moved into the ego
frame with complex arithmetic, their 4 edges become one (N*4) array of midpoints ``M`` and
half-vectors ``H``, and ray ``t*D`` meets edge ``M + u*H`` (|u| <= 1) where
``t = (M x H) / (D x H)``. All beams x all edges come out of a single matrix product that
yields ``q = 1/t`` and ``p = u/t``; a hit is ``|p| <= q`` and the first hit is the largest
``q``. No division by zero occurs and there is no Python loop over beams or objects.

Performance: ``scan`` with 20 objects and 240 beams measured ~57 us per call on the
development machine (2 CPU cores, numpy 2.4, ``timeit``, best of 5 x 20000 calls).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np


class EgoLidar:
    """Ego-framed 2-D lidar over oriented rectangles; see the module docstring."""

    def __init__(self, beams: int = 240, max_range: float = 50.0) -> None:
        if isinstance(beams, bool) or int(beams) != beams or beams < 1:
            raise ValueError(f"beams must be an integer >= 1, got {beams!r}")
        if not math.isfinite(max_range) or max_range <= 0:
            raise ValueError(f"max_range must be a finite number > 0, got {max_range!r}")
        self.beams = int(beams)
        self.max_range = float(max_range)
        angles = 2.0 * np.pi * np.arange(self.beams) / self.beams
        # Beam unit vectors relative to the ego heading, rows [cos; sin]: shape (2, beams).
        self._dirs = np.stack([np.cos(angles), np.sin(angles)])

    def scan(
        self,
        ego_position: np.ndarray,
        ego_heading: float,
        centres: np.ndarray,
        headings: np.ndarray,
        lengths: np.ndarray,
        widths: np.ndarray,
    ) -> np.ndarray:
        """Return float32 ``(beams,)`` in [0, 1]: distance to the first hit / max_range,
        1.0 where nothing is hit within range.

        Beam i points at angle ego_heading + 2*pi*i/beams (beam 0 = straight ahead,
        indices increase with the math angle). ``centres`` is (N, 2); ``headings``,
        ``lengths`` and ``widths`` are (N,)."""
        ego = np.asarray(ego_position, dtype=np.float64).reshape(-1)
        if ego.shape != (2,):
            raise ValueError(f"ego_position must have shape (2,), got {ego.shape}")
        c = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 2)
        h = np.asarray(headings, dtype=np.float64).reshape(-1)
        hl = 0.5 * np.asarray(lengths, dtype=np.float64).reshape(-1)
        hw = 0.5 * np.asarray(widths, dtype=np.float64).reshape(-1)
        if not len(h) == len(hl) == len(hw) == len(c):
            raise ValueError(
                "centres, headings, lengths and widths must have the same length, got "
                f"{len(c)}, {len(h)}, {len(hl)}, {len(hw)}"
            )
        if len(c) == 0:
            return np.ones(self.beams, dtype=np.float32)

        # Object centres in the ego frame as complex numbers; drop those out of reach.
        to_ego = complex(math.cos(ego_heading), -math.sin(ego_heading))
        z = (c.view(np.complex128).ravel() - complex(ego[0], ego[1])) * to_ego
        keep = np.abs(z) <= self.max_range + np.hypot(hl, hw)
        if not keep.all():
            z, h, hl, hw = z[keep], h[keep], hl[keep], hw[keep]
            if len(z) == 0:
                return np.ones(self.beams, dtype=np.float32)
        w = np.exp(1j * (h - ego_heading))  # object heading in the ego frame, unit complex

        # Ego centre inside an object (|centre in object frame| within the half sizes).
        g = z * w.conj()
        if np.any((np.abs(g.real) <= hl) & (np.abs(g.imag) <= hw)):
            return np.zeros(self.beams, dtype=np.float32)

        # (N*4) edges: midpoints z +- a, z +- b with half-vectors b, b, a, a.
        a, b = w * hl, w * (1j * hw)
        mid = np.concatenate([z + a, z - a, z + b, z - b])
        half = np.concatenate([b, b, a, a])
        num = (mid.conj() * half).imag  # M x H; 0 only when the edge's line hits the origin
        inv = np.divide(1.0, num, out=np.zeros_like(num), where=num != 0.0)
        # Complex coefficients whose (re, im) pairs dotted with D give q = (D x H) / (M x H)
        # = 1/t and p = (M x D) / (M x H) = u/t.
        m = len(mid)
        coef = np.empty(2 * m, dtype=np.complex128)
        np.multiply(half, -1j * inv, out=coef[:m])
        np.multiply(mid, 1j * inv, out=coef[m:])
        qp = coef.view(np.float64).reshape(2 * m, 2) @ self._dirs  # (2m, beams)
        q, p = qp[:m], qp[m:]
        q_first = (q * (np.abs(p) <= q)).max(axis=0)  # 1 / distance to first hit (0: none)
        return (1.0 / np.maximum(self.max_range * q_first, 1.0)).astype(np.float32)

    def scan_objects(self, ego: Any, objects: Iterable[Any]) -> np.ndarray:
        """Convenience: objects are highway-env RoadObject/Vehicle instances (attributes
        position, heading, LENGTH, WIDTH); the ego (also such an object) is excluded if
        present in the list. Delegates to scan()."""
        others = [o for o in objects if o is not ego]
        return self.scan(
            np.asarray(ego.position, dtype=np.float64),
            float(ego.heading),
            np.array([o.position for o in others], dtype=np.float64).reshape(-1, 2),
            np.array([o.heading for o in others], dtype=np.float64),
            np.array([o.LENGTH for o in others], dtype=np.float64),
            np.array([o.WIDTH for o in others], dtype=np.float64),
        )
