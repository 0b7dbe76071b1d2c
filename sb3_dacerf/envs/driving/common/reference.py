"""Reference path of the ego: a polyline sampled from highway-env lanes, with arc-length lookups."""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import AbstractLane


def nominal_steering(curvature: float, length: float) -> float:
    """The front-wheel angle [rad] with which highway-env's bicycle model (axles at ± length / 2) drives a curvature [1/m]."""
    beta = math.asin(min(max(curvature * length / 2, -1.0), 1.0))
    return math.atan(2.0 * math.tan(beta))


class ReferencePath:
    """A polyline of (N, 2) world positions [m] (no repeated points) and their (N,) headings, with arc-length lookups."""

    def __init__(self, points: np.ndarray, headings: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.headings = np.unwrap(np.asarray(headings, dtype=np.float64))
        segments = np.diff(self.points, axis=0)
        self.s = np.concatenate(([0.0], np.cumsum(np.hypot(segments[:, 0], segments[:, 1]))))
        self.curvatures = np.gradient(self.headings, self.s)
        self._point_list, self._s_list = self.points.tolist(), self.s.tolist()

    @classmethod
    def from_lanes(cls, pieces: list[tuple[AbstractLane, float, float]], step: float) -> ReferencePath:
        """The centre lines of consecutive ``(lane, start, end)`` longitudinal ranges [m], sampled every ``step`` m."""
        points, headings = [], []
        for i, (lane, start, end) in enumerate(pieces):
            # The last piece keeps its end point; the others leave it to the next piece's start.
            s_values = np.arange(start, end, step)
            if i == len(pieces) - 1:
                s_values = np.append(s_values, end)
            points += [lane.position(s, 0.0) for s in s_values]
            headings += [lane.heading_at(s) for s in s_values]
        return cls(np.array(points), np.array(headings))

    def project(self, position: np.ndarray) -> tuple[float, float]:
        """:return: the arc length [m] of a world position's foot point on the path and its signed lateral offset [m]"""
        offsets = self.points - position
        i = int(np.argmin(np.einsum("ij,ij->i", offsets, offsets)))
        px, py = float(position[0]), float(position[1])
        best = (math.inf, 0.0, 0.0)
        # Scalar math: numpy's per-call cost dominates on 2-vectors.
        for j in (i - 1, i):
            if 0 <= j < len(self.points) - 1:
                (ax, ay), (bx, by) = self._point_list[j], self._point_list[j + 1]
                length = self._s_list[j + 1] - self._s_list[j]
                ux, uy = (bx - ax) / length, (by - ay) / length
                along = min(max((px - ax) * ux + (py - ay) * uy, 0.0), length)
                dx, dy = px - ax - along * ux, py - ay - along * uy
                distance = math.hypot(dx, dy)
                if distance < best[0]:
                    best = (distance, self._s_list[j] + along, ux * dy - uy * dx)
        return best[1], best[2]

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        :param s: arc lengths [m], a 1-d array (beyond both ends, the path goes on straight)
        :return: positions (K, 2) [m], headings (K,) [rad] and curvatures (K,) [1/m]
        """
        headings = np.interp(s, self.s, self.headings)
        positions = np.empty((len(s), 2))
        positions[:, 0], positions[:, 1] = np.interp(s, self.s, self.points[:, 0]), np.interp(s, self.s, self.points[:, 1])
        curvatures = np.interp(s, self.s, self.curvatures)
        if s[0] < 0.0 or s[-1] > self.s[-1]:
            beyond = np.where(s > self.s[-1], s - self.s[-1], np.minimum(s, 0.0))
            positions += beyond[:, None] * np.column_stack([np.cos(headings), np.sin(headings)])
            curvatures[beyond != 0.0] = 0.0
        return positions, headings, curvatures
