"""Timing part of ``objslam bench association`` (bench/association.py): NPDA on 10 x 10 boxes, with and without
warping, and re-clustering 2,000 feature vectors (raw HDBSCAN variants and the bounded ``Clusterer``)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console

from bench.report import markdown_table, record, show_table
from graph.geometry import inverse
from perception.clustering import ClusterConfig, Clusterer, bhattacharyya_matrix, cluster_labels
from perception.features import FeatureVector
from perception.frame import Detection
from perception.npda import NPDAConfig, assign, associate, association_matrix

if TYPE_CHECKING:
    from bench.association import Scene


def npda_10x10(scene: Scene, config: NPDAConfig, k: int, repeats: int = 30) -> tuple[float, float]:
    """Median ms of NPDA (matrix + assignment) for 10 x 10 same-class boxes, and of the full warped step."""
    rng = np.random.default_rng(0)
    h, w = scene.depth[0].shape

    def boxes() -> list[Detection]:
        size = rng.uniform(60, 160, (10, 2))
        x, y = rng.uniform(0, w - size[:, 0]), rng.uniform(0, h - size[:, 1])
        return [Detection("chair", 0.9, (x[n], y[n], x[n] + size[n, 0], y[n] + size[n, 1])) for n in range(10)]

    prev, cur = boxes(), boxes()
    dp, dc = scene.depth_m(0), scene.depth_m(k)
    T = inverse(scene.poses[k]) @ scene.poses[0]
    t_matrix, t_full = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        assign(association_matrix(prev, dp, cur, dc, replace(config, min_iou=0.0)), config)
        t1 = time.perf_counter()
        associate(prev, dp, cur, dc, scene.K, T, config)
        t_matrix.append(t1 - t0)
        t_full.append(time.perf_counter() - t1)
    return 1e3 * float(np.median(t_matrix)), 1e3 * float(np.median(t_full))


def synthetic_features(n: int = 2000, objects: int = 25, seed: int = 0) -> list[FeatureVector]:
    """``n`` feature vectors of ``objects`` objects over 8 classes, 8 tracks each (timing input)."""
    rng = np.random.default_rng(seed)
    labels = ["chair", "cup", "tv", "couch", "book", "bottle", "laptop", "potted plant"]
    centres = rng.uniform(0, 6, (objects, 3))
    out = []
    for q in range(n):
        o = q % objects
        var = rng.uniform(0.002, 0.02, 3)
        out.append(
            FeatureVector(
                centres[o] + rng.normal(0, 0.05, 3), np.diag(var), 400, labels[o % 8], o * 8 + (q // objects) % 8
            )
        )
    return out


def clustering_timing(config: ClusterConfig, repeats: int = 3) -> dict[str, float]:
    """Median ms to re-cluster 2,000 feature vectors: raw HDBSCAN variants and the bounded ``Clusterer``."""
    feats = synthetic_features()
    one_class = [replace(f, label="chair") for f in feats]
    means, var = np.array([f.mean for f in feats]), np.array([f.var for f in feats])
    labels = [f.label for f in feats]

    def recluster(vectors: list[FeatureVector]) -> None:
        cl = Clusterer(config)
        cl.add(vectors)
        cl.recluster()

    runs = {
        "distance matrix only (2000 x 2000)": lambda: bhattacharyya_matrix(means, var, labels),
        "global matrix + HDBSCAN, N = 2000": lambda: cluster_labels(feats, replace(config, per_class=False)),
        "per-class matrices + HDBSCAN, N = 2000": lambda: cluster_labels(feats, config),
        f"Clusterer.recluster (default: per class, N <= {config.max_features} by track pooling)": lambda: recluster(
            feats
        ),
        "Clusterer.recluster, all 2000 vectors of one class": lambda: recluster(one_class),
    }
    out: dict[str, float] = {}
    for name, fn in runs.items():
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[name] = 1e3 * float(np.median(times))
    return out


def record_timing(console: Console, timing: dict[str, float], command: str, write: Path | None) -> None:
    targets = {
        name: ("<= 5 ms" if name.startswith("NPDA 10 x 10 (") else "<= 100 ms")
        for name in timing
        if name.startswith(("NPDA 10 x 10 (", "Clusterer"))
    }
    header = ["step", "median ms", "target"]
    rows = [[name, f"{ms:.1f}", targets.get(name, "")] for name, ms in timing.items()]
    show_table(console, "NPDA and clustering timing", header, rows)
    notes = (
        "NPDA: 10 previous x 10 current boxes of one class (no class pruning) on 640x480 synthetic depth; the "
        "second row adds warping the previous depth and boxes. Clustering: 2,000 feature vectors of 25 "
        "objects in 8 classes (last row: all relabelled one class, the worst case for per-class "
        "clustering); the Clusterer rows include track pooling, HDBSCAN, cluster merging and ellipsoids."
    )
    record("association-timing", "NPDA and re-clustering timing", command, markdown_table(header, rows), notes, write)
