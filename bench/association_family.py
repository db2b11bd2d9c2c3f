"""``objslam bench association --family``: NPDA between consecutive keyframes of held-out family scenes (issue 24).

The room scenes of ``bench association`` hold one object of a class here and there; the family's scenes hold rows
of chairs, cups, bottles and books 0.3-1.0 m apart, whose depths NPDA's U test cannot tell apart. Each scene's
keyframes are chosen on the true poses by the service's rule (as ``bench objects --family``) and every consecutive
pair is associated with the true relative pose, under each assignment rule (``NPDAConfig.rank_by``). A true
association joins two detections of one instance; a swap joins two instances of one class (the error that carries
a track from a chair to its neighbour and lets one cluster take a row).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from rich.console import Console

from bench.association import Counts, pct
from bench.objects_family import FAMILY_FRAMES, family_spec, keyframes
from bench.report import markdown_table, record, show_table
from graph.geometry import inverse
from perception.frame import Detection
from perception.keyframing import KeyframeSettings
from perception.npda import NPDAConfig, RankBy, associate
from sources.scene_family import HELD_OUT_SEEDS
from sources.synthetic import parse_synthetic_spec

RULES: dict[RankBy, str] = {
    "overlap": "one-to-one by the moved box's overlap, A breaking ties (default)",
    "score": "one-to-one on A alone (Hungarian on -A)",
}


@dataclass
class FamilyCounts(Counts):
    """Association outcomes with the swaps among the false positives: two instances of one class joined."""

    swaps: int = 0
    rows_tp: int = 0
    """True associations of detections whose keyframe holds another detection of their class."""
    rows_swaps: int = 0

    def add(self, other: Counts) -> None:
        super().add(other)
        if isinstance(other, FamilyCounts):
            self.swaps += other.swaps
            self.rows_tp += other.rows_tp
            self.rows_swaps += other.rows_swaps


def pair_outcome(
    prev: tuple[list[Detection], list[int]], cur: tuple[list[Detection], list[int]], pairs: list[tuple[int, int]]
) -> FamilyCounts:
    """Outcomes of the associated ``pairs`` between two keyframes' detections and true instance ids."""
    (pd, pi), (cd, ci) = prev, cur
    truth = {(m, n) for m in range(len(pi)) for n in range(len(ci)) if pi[m] and pi[m] == ci[n]}
    found = set(pairs)
    swaps = {(m, n) for m, n in found - truth if pi[m] and ci[n] and pd[m].label == cd[n].label}
    crowded = {n for n in range(len(cd)) if sum(d.label == cd[n].label for d in cd) > 1}
    return FamilyCounts(
        len(found & truth),
        len(found - truth),
        len(truth - found),
        len(swaps),
        sum(n in crowded for _, n in found & truth),
        sum(n in crowded for _, n in swaps),
    )


def scene_counts(seed: int, frames: int, rules: dict[RankBy, NPDAConfig]) -> tuple[dict[RankBy, FamilyCounts], int]:
    """Per rule, the outcomes over one family scene's consecutive keyframe pairs; and the number of pairs."""
    data = parse_synthetic_spec(family_spec(seed, frames))
    poses = data.ground_truth.poses
    out = {name: FamilyCounts() for name in rules}
    last = None
    chosen = keyframes(poses, KeyframeSettings())  # ascending, each once
    for i in chosen:
        frame = data.frame(i)
        now = (list(frame.detections or []), list(data.detection_instance_ids(i)), frame.depth_m(), poses[i])
        if last is not None:
            T = inverse(now[3]) @ last[3]
            for name, config in rules.items():
                result = associate(last[0], last[2], now[0], now[2], data.camera.color, T, config)
                out[name].add(pair_outcome(last[:2], now[:2], result.pairs))
        last = now
    return out, len(chosen) - 1


def run_association_family(console: Console, seeds: list[int], frames: int, write: Path | None) -> dict:
    """NPDA precision, recall and swaps per assignment rule over the family scenes ``seeds`` (module doc)."""
    start = time.perf_counter()
    rules = {name: replace(NPDAConfig(), rank_by=name) for name in RULES}
    totals = {name: FamilyCounts() for name in RULES}
    pairs = 0
    for seed in seeds:
        counts, n = scene_counts(seed, frames, rules)
        pairs += n
        for name, c in counts.items():
            totals[name].add(c)
        console.print(
            f"family seed {seed}: {n} keyframe pairs, swaps " + ", ".join(f"{k} {c.swaps}" for k, c in counts.items())
        )
    header = [
        "assignment",
        "keyframe pairs",
        "true associations",
        "precision %",
        "recall %",
        "swaps (two instances of one class)",
        "in keyframes with another of the class: associated right / swapped",
    ]
    rows = [
        [
            RULES[name],
            pairs,
            c.tp + c.fn,
            pct(c.precision),
            pct(c.recall),
            c.swaps,
            f"{c.rows_tp} / {c.rows_swaps} ({pct(c.rows_swaps / max(c.rows_tp + c.rows_swaps, 1))} % swapped)",
        ]
        for name, c in totals.items()
    ]
    show_table(console, "NPDA on the held-out scene family", header, rows)
    seconds = time.perf_counter() - start
    if write is not None:
        command = (
            "objslam bench association --family"
            + ("" if seeds == list(HELD_OUT_SEEDS) else " --seeds " + ",".join(map(str, seeds)))
            + (f" --frames {frames}" if frames != FAMILY_FRAMES else "")
        )
        notes = (
            f"Scenes `synthetic:family?seed=N&frames={frames}` (held-out seeds unless named), keyframes by the "
            "service's rule on the true poses (5 cm, 5 degrees or 10 frames), each consecutive pair associated with "
            "the true relative pose and NPDA's defaults but for the assignment. A true association joins two "
            "detections of one instance (false-positive detections have id 0 and count as errors when associated); "
            f"a swap joins two instances of one class. {len(seeds)} scenes in {seconds:.0f} s."
        )
        record(
            "association-family",
            "NPDA on the held-out scene family",
            command,
            markdown_table(header, rows),
            notes,
            write,
        )
    return {name: vars(c) for name, c in totals.items()}
