"""Measurement model of a laser-tracker-like instrument (pure functions; the emulator process is built on these).

The instrument stands somewhere in the cell and reports in its OWN frame. Each reflector position it reads has
independent normal noise per axis with standard deviation ``15 um + 6 um/m * distance`` (the instrument's
"+-15 um + 6 um/m" taken as one sigma, the conservative reading). A pose (6-DoF) is what its probe software
reports: the rigid fit of several reflectors fixed on the tool, so orientation noise follows from the reflector
spread."""

from __future__ import annotations

import numpy as np

SIGMA_0 = 15e-6  # m
SIGMA_PER_M = 6e-6  # m per m of distance from the instrument


def sigma(distance) -> np.ndarray:
    """Per-axis standard deviation (m) of a reading at ``distance`` (m) from the instrument."""
    return SIGMA_0 + SIGMA_PER_M * np.asarray(distance, dtype=float)


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def measure_points(points_base, tracker_in_base, rng: np.random.Generator) -> np.ndarray:
    """Reflector positions ``(N, 3)`` (true, robot base frame) as the instrument reports them: in its own frame
    (``tracker_in_base`` = its pose in the base frame, 4x4), with distance-dependent noise."""
    p = np.atleast_2d(np.asarray(points_base, dtype=float))
    inv = _inverse(np.asarray(tracker_in_base, dtype=float))
    local = p @ inv[:3, :3].T + inv[:3, 3]
    s = sigma(np.linalg.norm(local, axis=1))
    return local + rng.standard_normal(local.shape) * s[:, None]


def measure_poses(tool_in_base, reflectors_on_tool, tracker_in_base, rng: np.random.Generator) -> np.ndarray:
    """Tool poses ``(N, 4, 4)`` (true, base frame) as a 6-DoF probe reports them in the instrument frame: each of
    the ``K >= 3`` reflectors ``(K, 3)`` (tool frame) is read with noise and the tool frame is the least-squares
    rigid fit (Kabsch) of the nominal reflector layout to the readings."""
    T = np.asarray(tool_in_base, dtype=float).reshape(-1, 4, 4)
    r = np.asarray(reflectors_on_tool, dtype=float)
    if r.ndim != 2 or r.shape[0] < 3 or r.shape[1] != 3:
        raise ValueError("a 6-DoF probe needs at least 3 reflectors [x, y, z] on the tool")
    out = np.zeros_like(T)
    centred = r - r.mean(axis=0)
    for i, Ti in enumerate(T):
        pts = measure_points(r @ Ti[:3, :3].T + Ti[:3, 3], tracker_in_base, rng)
        c = pts.mean(axis=0)
        H = centred.T @ (pts - c)
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
        out[i, :3, :3] = R
        out[i, :3, 3] = c - R @ r.mean(axis=0)
        out[i, 3, 3] = 1.0
    return out
