"""The synthetic scene family (``synthetic:family``): determinism, the ranges the layouts honour, the camera paths'
clearance and yaw-rate cap, rendering, the held-out seed list and the family benchmark's plumbing."""

from __future__ import annotations

import io
import itertools

import numpy as np
import pytest
from rich.console import Console

from bench.objects_family import family_seeds, keyframes, run_family_bench, worst_decile
from perception.keyframing import KeyframeSettings
from sources.family_paths import MAX_YAW_RATE_DEG_S, PATH_KINDS, heading_rates_deg_s
from sources.family_render import plain_texture
from sources.raycast import surface_texture
from sources.scene_family import (
    CLEARANCE_M,
    DEVELOPMENT_SEEDS,
    HELD_OUT_SEEDS,
    ROW_LABELS,
    SPACING_BUCKETS_M,
    FamilyLayout,
    family_poses,
    make_layout,
    size_class,
)
from sources.synthetic import SyntheticDataset, parse_synthetic_spec
from tests.test_synthetic import backproject, boxes_overlap, footprint, iou, mask_box

SEEDS = range(40)  # property checks (neither tuning nor benchmark)
SMALL = "synthetic:family?seed=3&frames=120&width=320&height=240"


@pytest.fixture(scope="module")
def layouts() -> list[FamilyLayout]:
    return [make_layout(s) for s in SEEDS]


@pytest.fixture(scope="module")
def small() -> SyntheticDataset:
    return parse_synthetic_spec(SMALL)


def test_layout_and_frames_are_deterministic_per_seed_and_seeds_differ(small: SyntheticDataset) -> None:
    assert make_layout(5) == make_layout(5) and make_layout(5) != make_layout(6)
    other = parse_synthetic_spec(SMALL)
    late, early = other.frame(90), other.frame(4)  # reverse order, fresh instance
    for i, f2 in ((4, early), (90, late)):
        f1 = small.frame(i)
        assert np.array_equal(f1.rgb, f2.rgb) and np.array_equal(f1.depth, f2.depth)
        assert f1.detections == f2.detections and np.array_equal(f1.odometry, f2.odometry)
    assert np.array_equal(small.ground_truth.poses, other.ground_truth.poses) and small.objects == other.objects
    seeded = parse_synthetic_spec(SMALL.replace("seed=3", "seed=4"))
    assert not np.array_equal(seeded.frame(4).rgb, early.rgb)
    assert [o.center for o in seeded.objects] != [o.center for o in small.objects]
    # the layout depends on the seed only, not on the sequence's length or rate
    longer = parse_synthetic_spec("synthetic:family?seed=3&frames=400&fps=15&width=64&height=48")
    assert longer.objects == small.objects and longer.family == small.family


def test_rooms_rows_and_size_classes_honour_their_ranges(layouts: list[FamilyLayout]) -> None:
    spacings, labels, lengths = [], set(), set()
    for lay in layouts:
        w, d, h = lay.room
        assert 4.0 <= w <= 9.0 and 4.0 <= d <= 9.0 and 2.5 <= h <= 3.0
        by_id = {o.id: o for o in lay.objects}
        assert [o.id for o in lay.objects] == list(range(1, len(lay.objects) + 1))
        assert len(lay.rows) >= 2, lay.seed  # rows of same-class objects in every scene
        for row in lay.rows:
            members = [by_id[i] for i in row.ids]
            assert 2 <= len(members) <= 5 and row.label in ROW_LABELS
            assert {o.label for o in members} == {row.label}
            assert 0.3 <= row.spacing_m <= 1.0 and abs(row.spacing_m - row.bucket) <= 0.02 + 1e-9
            gaps = [np.linalg.norm(np.subtract(a.center[:2], b.center[:2])) for a, b in itertools.pairwise(members)]
            assert np.allclose(gaps, row.spacing_m, atol=0.035), (lay.seed, row)
            spacings.append(row.bucket)
            labels.add(row.label)
            lengths.add(len(members))
        classes = [size_class(o) for o in lay.objects]
        assert {"small", "large"} <= set(classes), lay.seed
        for o, c in zip(lay.objects, classes, strict=True):
            side = max(o.size[:2])
            assert (c == "small") == (side < 0.1) and (c == "large") == (side > 1.0)
        assert len(lay.pairs()) == sum(len(r.ids) - 1 for r in lay.rows)
    assert set(spacings) == set(SPACING_BUCKETS_M) and labels == set(ROW_LABELS) and lengths == {2, 3, 4, 5}
    assert any(lay.plain_walls for lay in layouts) and not all(lay.plain_walls for lay in layouts)


def test_objects_stay_in_the_room_apart_and_rest_on_their_supports(layouts: list[FamilyLayout]) -> None:
    cluttered = 0
    for lay in layouts:
        objects = list(lay.objects)
        for k, a in enumerate(objects):
            fp = footprint(a)
            assert fp.min() > 0 and (fp < lay.room[:2]).all() and a.center[2] + a.size[2] / 2 < lay.room[2]
            assert not any(boxes_overlap(a, b) for b in objects[k + 1 :]), (lay.seed, a)
        tables = [o for o in objects if o.label == "dining table"]
        assert tables, lay.seed
        for t in tables:  # objects on a table: their bottom on its top, their footprint inside its own
            top = t.center[2] + t.size[2] / 2
            on = [o for o in objects if abs(o.center[2] - o.size[2] / 2 - top) < 1e-9 and o is not t]
            on = [o for o in on if np.all(np.abs(footprint(o) - t.center[:2]) <= max(t.size[:2]))]
            cluttered += len(on) >= 3
    assert cluttered >= len(layouts)


def test_every_path_kind_keeps_clear_of_objects_under_the_yaw_rate_cap(layouts: list[FamilyLayout]) -> None:
    seen = set()
    for lay in layouts[:16]:
        seen.add(lay.path.kind)
        poses = family_poses(lay, 900, 30.0, 1.15)
        pos = poses[:, :3, 3]
        assert np.allclose(poses[:, 3], [0, 0, 0, 1])
        rates = heading_rates_deg_s(poses, 30.0)
        assert rates.max() <= MAX_YAW_RATE_DEG_S, (lay.seed, rates.max())
        assert np.linalg.norm(np.diff(pos, axis=0), axis=1).max() * 30.0 <= 1.05  # <= 1 m/s, tremor aside
        assert pos[:, 2].min() >= 1.1 and pos[:, 2].max() <= 1.8
        assert pos[:, :2].min() >= 0.9 and (lay.room[:2] - pos[:, :2].max(axis=0) >= 0.9).all()
        for o in lay.objects:
            c, s = np.cos(o.yaw), np.sin(o.yaw)
            d = pos[:, :2] - o.center[:2]
            local = np.abs(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1))
            clearance = np.linalg.norm(np.maximum(local - np.array(o.size[:2]) / 2, 0), axis=1).min()
            assert clearance >= CLEARANCE_M, (lay.seed, o.label, clearance)
    assert seen == set(PATH_KINDS)
    # fast scenes exist: the sweeps turn at 40-60 deg/s
    sweep = next(lay for lay in layouts if lay.path.kind == "sweep")
    assert heading_rates_deg_s(family_poses(sweep, 300, 30.0, 1.15), 30.0).max() >= 30.0


def test_paths_revisit_and_ground_truth_has_loops() -> None:
    for seed in range(4):
        ds = SyntheticDataset("family", seed=seed, frames=900, width=32, height=32)
        assert ds.family is not None and len(ds.loops) >= 20, (seed, ds.family.path.kind)
        assert all(j - i >= 100 for i, j in ds.loops)


def test_family_frames_are_valid_renders(small: SyntheticDataset) -> None:
    assert small.name == "synthetic/family" and len(small) == 120 and small.family is not None
    poses, objects = small.ground_truth.poses, {o.id: o for o in small.objects}
    visible = checked = 0
    for i in range(0, 120, 15):
        f, mask = small.frame(i), small.instance_mask(i)
        assert f.frame_id == f"synthetic/family/{i:06d}" and f.rgb.shape == (240, 320, 3) and f.depth.dtype == np.uint16
        depth = f.depth_m()
        assert np.isfinite(depth).mean() > 0.5 and np.nanmax(depth) <= 4.2 and f.rgb.std() > 5
        pts, flat = backproject(small, depth, poses[i])
        ids = mask.ravel()[flat]
        for oid in np.unique(ids[ids > 0]):
            if (ids == oid).sum() < 100:  # a few pixels of depth noise (sigma 1-3 cm far away) decide it
                continue
            o = objects[int(oid)]
            c, s = np.cos(o.yaw), np.sin(o.yaw)
            d = pts[ids == oid] - np.array(o.center)
            local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
            assert np.all(np.abs(local) <= np.array(o.size) / 2 + 0.05, axis=1).mean() >= 0.95
            checked += 1
        for det, oid in zip(f.detections, small.detection_instance_ids(i), strict=True):
            if oid:
                visible += 1
                assert det.label == objects[oid].label and iou(det.box, mask_box(mask == oid)) >= 0.7
    assert checked >= 10 and visible >= 10


def test_plain_walls_are_texture_poor() -> None:
    rng = np.random.default_rng(0)
    plain, rich = plain_texture(rng, 3.0, 2.5), surface_texture(rng, 3.0, 2.5)
    grad = lambda t: np.abs(np.diff(t.astype(float), axis=1)).mean()
    assert grad(plain) < 0.2 * grad(rich) and plain.std() < 10
    lay = next(make_layout(s) for s in SEEDS if make_layout(s).plain_walls)
    ds = SyntheticDataset("family", seed=lay.seed, frames=4, width=32, height=32)
    walls = ds.surfaces[:4]
    assert all(s.texture.std() < 25 for s in walls) and ds.surfaces[4].texture.std() > 25


def test_held_out_seeds_are_many_distinct_and_not_for_tuning() -> None:
    assert len(HELD_OUT_SEEDS) >= 20 and len(set(HELD_OUT_SEEDS)) == len(HELD_OUT_SEEDS)
    assert DEVELOPMENT_SEEDS and not set(HELD_OUT_SEEDS) & set(DEVELOPMENT_SEEDS)
    assert {PATH_KINDS[s % 4] for s in HELD_OUT_SEEDS} == set(PATH_KINDS)
    assert family_seeds(None) == list(HELD_OUT_SEEDS) and family_seeds("dev") == list(DEVELOPMENT_SEEDS)
    assert family_seeds("3, 5") == [3, 5]


def test_spec_knobs_and_errors() -> None:
    ds = parse_synthetic_spec("synthetic:family?seed=2&frames=30&width=80&height=60&fps=15&miss_rate=0.2&fp_rate=0")
    assert (ds.seed, len(ds), ds.fps, ds.miss_rate, ds.fp_rate) == (2, 30, 15.0, 0.2, 0.0)
    assert ds.frame(3).timestamp == pytest.approx(0.2) and ds.ground_truth.poses.shape == (30, 4, 4)
    assert parse_synthetic_spec("synthetic:room?frames=2&width=32&height=32").family is None
    with pytest.raises(Exception, match="seed"):
        parse_synthetic_spec("synthetic:family?seed=-1")


def test_bench_keyframes_deciles_and_a_small_run(tmp_path) -> None:
    poses = np.tile(np.eye(4), (25, 1, 1))
    poses[:, 0, 3] = np.arange(25) * 0.02  # 2 cm a frame: every third frame moves 5 cm or more
    assert keyframes(poses, KeyframeSettings()) == [0, 3, 6, 9, 12, 15, 18, 21, 24]
    assert worst_decile(list(range(11)), True) == 1.0 and worst_decile(list(range(11)), False) == 9.0
    out = io.StringIO()
    result = run_family_bench(Console(file=out, width=200), [1], 60, None, min_frames=3, size=(160, 120))
    scene = result["per_scene"][1]
    assert scene["present"] >= 1 and 0 <= scene["mapped_pct"] <= 100 and scene["keyframes"] >= 6
    assert "IoU by size class" in out.getvalue() and not (tmp_path / "b.md").exists()
    run_family_bench(Console(file=io.StringIO()), [1], 60, tmp_path / "b.md", min_frames=3, size=(160, 120))
    assert "<!-- bench:objects-family -->" in (tmp_path / "b.md").read_text()
