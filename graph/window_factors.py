"""The window's arithmetic (``graph.window``): which factors a window holds, factors on fixed keyframes as unary
factors on the window side, and the fixed past re-anchored at a whole-graph solve.

A window from keyframe ``start`` holds keyframes ``[start, n)``; those before it are *fixed* at ``fixed[k]``.
A between-factor a -> b with ``a`` fixed is a prior ``T_a @ T_ab`` on ``b`` with the same noise and kernel, with
``b`` fixed a prior ``T_b @ T_ab^-1`` on ``a`` whose covariance is carried through ``Ad(T_ab)`` (both exact); a
landmark measured from a fixed keyframe is a world-position prior on the landmark with the measurement's
covariance rotated into the world (to first order the bearing-range factor's: isotropic, or wider along the
viewing ray).
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence, Set
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from graph.factors import FactorKind, FactorRecord, pose_noise, position_covariance

Estimate = tuple[np.ndarray, dict[int, np.ndarray]]
"""Keyframe poses (K, 4, 4) and landmark positions by id."""


def ends(f: FactorRecord) -> list[tuple[int | None, int | None]]:
    """(keyframe, landmark) of each variable a factor constrains (one of the two is None)."""
    if f.kind == FactorKind.LANDMARK:
        return [(None, f.a)] if f.b is None else [(f.a, None), (None, f.b)]
    return [(f.a, None)] if f.b is None else [(f.a, None), (f.b, None)]


def landmarks_of(factors: Iterable[FactorRecord]) -> set[int]:
    """The landmarks these factors constrain."""
    return {j for f in factors for _, j in ends(f) if j is not None}


class FactorIndex:
    """Factor indices by the keyframes and landmarks they constrain."""

    def __init__(self) -> None:
        self._by_keyframe: dict[int, list[int]] = {}
        self._by_landmark: dict[int, list[int]] = {}

    def add(self, factors: Sequence[FactorRecord], first: int) -> None:
        """Index factors numbered from ``first``."""
        for i, f in enumerate(factors, start=first):
            for k, j in ends(f):
                if k is not None:
                    self._by_keyframe.setdefault(k, []).append(i)
                if j is not None:
                    self._by_landmark.setdefault(j, []).append(i)

    def on_keyframe(self, k: int) -> list[int]:
        return self._by_keyframe.get(k, [])

    def on_landmark(self, j: int) -> list[int]:
        return self._by_landmark.get(j, [])


def localize(f: FactorRecord, start: int, fixed: np.ndarray, landmarks: Collection[int]) -> FactorRecord | None:
    """A factor in the keyframe ids of the window from ``start`` (keyframe ``start`` is its 0); one on a fixed
    keyframe as a prior on its other end; None when nothing of it is in the window (both keyframes fixed, or a
    landmark not in ``landmarks``)."""
    s = start
    if f.kind == FactorKind.LANDMARK:
        if f.b is None:
            return f if f.a in landmarks else None
        if f.b not in landmarks:
            return None
        if f.a >= s:
            return replace(f, a=f.a - s)
        T = fixed[f.a]
        R = T[:3, :3]
        covariance = (
            None
            if f.range_sigma_m is None
            else R @ position_covariance(f.measurement, f.sigma_m, f.range_sigma_m) @ R.T
        )
        return FactorRecord(
            f.b, None, R @ f.measurement + T[:3, 3], f.sigma_m, 0.0, f.huber_k, FactorKind.LANDMARK, covariance
        )
    if f.b is None:
        return replace(f, a=f.a - s) if f.a >= s else None
    if f.a >= s and f.b >= s:
        return replace(f, a=f.a - s, b=f.b - s)
    if f.b >= s:
        return replace(f, a=f.b - s, b=None, measurement=fixed[f.a] @ f.measurement)
    if f.a >= s:  # the prior's error is -Ad(T_ab) times the between-factor's: its covariance transformed so
        adjoint = gtsam.Pose3(f.measurement).AdjointMap()
        covariance = f.covariance if f.covariance is not None else pose_noise(f.sigma_m, f.sigma_deg).covariance()
        return replace(
            f,
            b=None,
            a=f.a - s,
            measurement=fixed[f.b] @ np.linalg.inv(f.measurement),
            covariance=adjoint @ covariance @ adjoint.T,
        )
    return None


def window_factors(
    index: FactorIndex,
    factors: Sequence[FactorRecord],
    removed: Collection[int],
    in_solver: Set[int],
    start: int,
    n_keyframes: int,
) -> tuple[list[int], set[int]]:
    """What a window from ``start`` holds: the live factors on its keyframes and on the landmarks it keeps (in
    factor order), and those landmarks (in the solver, and measured from a keyframe of the window)."""
    indices = sorted({i for k in range(start, n_keyframes) for i in index.on_keyframe(k) if i not in removed})
    kept = {
        f.b for f in (factors[i] for i in indices) if f.kind == FactorKind.LANDMARK and f.b is not None and f.a >= start
    }
    kept &= in_solver
    indices = sorted(set(indices) | {i for j in kept for i in index.on_landmark(j) if i not in removed})
    return indices, kept


def anchored(
    current: np.ndarray, landmarks: dict[int, np.ndarray], solved: Estimate | None, in_solver: Collection[int]
) -> Estimate:
    """Every keyframe and landmark estimate, from a whole-graph solve where it has them: keyframes and
    landmarks that came later move rigidly with the newest solved keyframe. ``current`` and ``landmarks``: the
    window's estimate; ``in_solver``: the landmarks that are in the graph."""
    n = 0 if solved is None else min(len(solved[0]), len(current))
    if solved is None or n == 0:
        return current, landmarks
    poses, solved_landmarks = solved
    correction = poses[n - 1] @ np.linalg.inv(current[n - 1])
    moved = np.concatenate([poses[:n], correction @ current[n:]])
    merged = {j: correction[:3, :3] @ p + correction[:3, 3] for j, p in landmarks.items()}
    merged.update({j: p for j, p in solved_landmarks.items() if j in in_solver})
    return moved, merged


FUSE_AT = 8
"""World priors on one landmark (its measurements from fixed keyframes) beyond this many are fused into one: a
landmark seen from every lap of a long run had thousands, rebuilt into the window at every roll."""


def is_world_prior(f: FactorRecord, local: FactorRecord) -> bool:
    """Whether ``local`` (``localize`` of ``f``) is a landmark measurement from a fixed keyframe as a prior."""
    return local.kind == FactorKind.LANDMARK and local.b is None and f.b is not None


def fused_prior(priors: Sequence[FactorRecord], at: np.ndarray) -> FactorRecord:
    """One world prior on a landmark that stands for ``priors`` (world-position priors on it, each robust or not)
    around ``at``: their information summed, each weighted as iteratively reweighted least squares weighs a
    Huber kernel at ``at`` (1 within ``huber_k`` whitened units, ``huber_k`` / error beyond). Gaussian priors
    fuse exactly; robust ones as their sum looks around ``at``, so the window keeps down what the whole graph's
    solve, with every measurement, would weigh down."""
    information, eta = np.zeros((3, 3)), np.zeros(3)
    for f in priors:
        covariance = f.covariance if f.covariance is not None else f.sigma_m**2 * np.eye(3)
        info = np.linalg.inv(covariance)
        r = np.asarray(f.measurement, float) - at
        error = float(np.sqrt(r @ info @ r))
        w = 1.0 if f.huber_k is None or error <= f.huber_k else f.huber_k / error
        information += w * info
        eta += w * info @ f.measurement
    covariance = np.linalg.inv(information)
    first = priors[0]
    return FactorRecord(first.a, None, covariance @ eta, first.sigma_m, 0.0, None, FactorKind.LANDMARK, covariance)


@dataclass
class Localized:
    """Factors for the window, and the whole-graph factors (indices) each one stands for."""

    factors: list[FactorRecord] = field(default_factory=list)
    owners: list[list[int]] = field(default_factory=list)

    def add(self, factor: FactorRecord, owners: list[int]) -> None:
        self.factors.append(factor)
        self.owners.append(owners)


def localized_factors(
    factors: Iterable[tuple[int, FactorRecord, FactorRecord]], landmarks: dict[int, np.ndarray], into: Localized
) -> None:
    """Add to ``into`` the window's factors for ``factors`` (index, whole-graph factor, its ``localize``d form)
    in order: a landmark's world priors beyond ``FUSE_AT`` fused into one (``fused_prior`` around its estimate in
    ``landmarks``), where its first one was."""
    given = list(factors)
    groups: dict[int, list[int]] = {}
    for n, (_, f, r) in enumerate(given):
        if is_world_prior(f, r):
            groups.setdefault(r.a, []).append(n)
    fused = {members[0]: members for members in groups.values() if len(members) > FUSE_AT}
    skip = {n for members in fused.values() for n in members[1:]}
    for n, (i, _, r) in enumerate(given):
        if n in fused:
            into.add(fused_prior([given[m][2] for m in fused[n]], landmarks[r.a]), [given[m][0] for m in fused[n]])
        elif n not in skip:
            into.add(r, [i])


def fused_owners(to_local: dict[int, int]) -> dict[int, list[int]]:
    """The window factors that stand for several whole-graph factors, with those (of whole -> window index)."""
    owners: dict[int, list[int]] = {}
    for i, li in to_local.items():
        owners.setdefault(li, []).append(i)
    return {li: members for li, members in owners.items() if len(members) > 1}
