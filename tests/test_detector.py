"""The ONNX detector: decoders on constructed outputs, regression on photos shipped with scikit-image / matplotlib."""

from __future__ import annotations

import io
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import onnxruntime
import pytest
from matplotlib import cbook
from pydantic import ValidationError
from rich.console import Console
from skimage import data

from bench.detector import run_detector_bench
from perception.centernet_input import ReshapeError, reshaped_centernet
from perception.coco import COCO_CLASSES
from perception.detector import Detector, DetectorSettings, default_model_path
from perception.detector_decoders import (
    InputTransform,
    decode_centernet,
    decode_nanodet,
    decode_yolo,
    fitted_height,
    letterbox,
    nms,
    select,
    stretch,
)
from perception.frame import Detection

# Hand-measured object boxes (x1, y1, x2, y2) in image pixels, read off annotated renders with a 50 px grid.
CAT_CHELSEA = (0.0, 0.0, 451.0, 300.0)  # the cat fills the frame
CUP_COFFEE = (172.0, 22.0, 412.0, 300.0)  # rim to handle, saucer excluded
PERSON_ASTRONAUT = (10.0, 10.0, 370.0, 512.0)
MOTORCYCLE = (95.0, 85.0, 678.0, 440.0)  # rear fender to front wheel, mirrors to tyres
PERSON_HOPPER = (0.0, 20.0, 512.0, 600.0)


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def grace_hopper() -> np.ndarray:
    path = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


# --- pre-processing -----------------------------------------------------------------------------


def test_letterbox_centres_the_resized_image_and_the_transform_inverts_it():
    image = np.full((100, 200, 3), 255, np.uint8)
    canvas, tf = letterbox(image, 64, pad_value=114)
    assert canvas.shape == (64, 64, 3)
    assert (tf.sx, tf.sy, tf.pad_x, tf.pad_y) == (0.32, 0.32, 0.0, 16.0)
    assert (canvas[:16] == 114).all() and (canvas[48:] == 114).all() and (canvas[16:48] == 255).all()
    box_in_input = np.array([[0.0, 16.0, 64.0, 48.0], [32.0, 32.0, 48.0, 40.0]])
    np.testing.assert_allclose(tf.to_image(box_in_input), [[0, 0, 200, 100], [100, 50, 150, 75]])


def test_stretch_scales_each_axis_separately():
    resized, tf = stretch(np.zeros((100, 200, 3), np.uint8), 50)
    assert resized.shape == (50, 50, 3) and (tf.sx, tf.sy) == (0.25, 0.5)
    np.testing.assert_allclose(tf.to_image(np.array([[5.0, 5.0, 25.0, 50.0]])), [[20, 10, 100, 100]])


# --- decoders -----------------------------------------------------------------------------------


def test_decode_centernet_reads_rows_of_box_score_class():
    rows = np.zeros((1, 100, 6), np.float32)
    rows[0, 0] = [10, 20, 110, 220, 0.8, 41]
    rows[0, 1] = [5, 5, 50, 50, 0.4, 56]
    boxes, scores, classes = decode_centernet(rows)
    assert boxes.shape == (100, 4)
    np.testing.assert_allclose(boxes[0], [10, 20, 110, 220])
    assert scores[0] == pytest.approx(0.8) and classes[:2].tolist() == [41, 56]


def _nanodet_outputs(size: int, bins: int = 11) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Empty NanoDet heads (cls, reg) per stride: all scores 0, all distance logits equal."""
    out = {}
    for stride in (8, 16, 32):
        cells = (size // stride) ** 2
        out[stride] = (np.zeros((1, cells, 80), np.float32), np.zeros((1, cells, 4 * bins), np.float32))
    return out


def test_decode_nanodet_measures_distances_from_cell_centres_in_row_major_order():
    heads = _nanodet_outputs(64)
    cls, reg = heads[8]
    cell = 2 * 8 + 3  # row 2, column 3 of the 8x8 stride-8 grid: centre (28, 20)
    cls[0, cell, 62] = 0.9
    for side, dist_bins in enumerate((2, 1, 3, 4)):  # left, top, right, bottom, one-hot
        reg[0, cell, side * 11 + dist_bins] = 50.0
    outputs = [heads[32][1], heads[8][0], heads[16][0], heads[8][1], heads[32][0], heads[16][1]]  # any order
    boxes, scores, classes = decode_nanodet(outputs, 64)
    assert boxes.shape == (64 + 16 + 4, 4)
    best = int(scores.argmax())
    assert best == cell and classes[best] == 62 and scores[best] == pytest.approx(0.9)
    np.testing.assert_allclose(boxes[best], [28 - 16, 20 - 8, 28 + 24, 20 + 32], atol=1e-3)


def test_decode_nanodet_takes_the_expectation_over_bins():
    heads = _nanodet_outputs(64)
    reg = heads[32][1]
    reg[0, 3, 0:2] = 100.0  # left: bins 0 and 1 equally likely -> 0.5 bins
    boxes, _, _ = decode_nanodet([a for pair in heads.values() for a in pair], 64)
    stride32 = boxes[64 + 16 :]
    centre = (1 + 0.5) * 32, (1 + 0.5) * 32  # cell 3 = row 1, column 1 of the 2x2 grid
    assert stride32[3, 0] == pytest.approx(centre[0] - 0.5 * 32, abs=1e-3)
    assert stride32[3, 2] == pytest.approx(centre[0] + 5.0 * 32, abs=1e-3)  # uniform over 11 bins: mean 5


def test_decode_yolo_converts_centre_size_and_accepts_both_layouts():
    out = np.zeros((1, 84, 10), np.float32)
    out[0, :4, 7] = [100, 50, 40, 20]
    out[0, 4 + 41, 7] = 0.9
    out[0, 4 + 56, 7] = 0.3
    for tensor in (out, out.transpose(0, 2, 1)):
        boxes, scores, classes = decode_yolo(tensor, num_classes=80)
        assert boxes.shape == (10, 4)
        np.testing.assert_allclose(boxes[7], [80, 40, 120, 60])
        assert classes[7] == 41 and scores[7] == pytest.approx(0.9)
    many = np.zeros((1, 84, 8400), np.float32)  # without the class count: anchors outnumber channels
    assert decode_yolo(many)[0].shape == (8400, 4)


def test_letterbox_undo_maps_a_yolo_box_back_to_the_image():
    _, tf = letterbox(np.zeros((480, 640, 3), np.uint8), 640, 114)  # pad 80 rows above and below
    out = np.zeros((1, 84, 1), np.float32)
    out[0, :4, 0] = [320, 320, 64, 64]
    boxes, _, _ = decode_yolo(out, num_classes=80)
    np.testing.assert_allclose(tf.to_image(boxes), [[288, 208, 352, 272]])


# --- thresholds and NMS -------------------------------------------------------------------------


def test_nms_suppresses_overlaps_within_a_class_only():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    classes = np.array([1, 1, 2, 1])
    assert nms(boxes, scores, classes, iou=0.5, max_det=10).tolist() == [0, 2, 3]
    assert nms(boxes, scores, classes, iou=0.9, max_det=10).tolist() == [0, 1, 2, 3]
    assert nms(boxes, scores, classes, iou=0.5, max_det=2).tolist() == [0, 2]


def test_select_applies_per_class_thresholds_and_drops_degenerate_boxes():
    boxes = np.array([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10], [60, 0, 60, 10], [70, 0, 80, 10]], np.float32)
    scores = np.array([0.5, 0.5, 0.35, 0.9, 1.0], np.float32)
    classes = np.array([0, 1, 2, 2, 3])
    thresholds = np.array([0.3, 0.6, 0.3, np.inf, 0.3], np.float32)  # class 3 is not on the allow-list
    assert select(boxes, scores, classes, thresholds, 0.5, 10).tolist() == [0, 2]


def test_input_transform_is_the_inverse_of_the_forward_mapping():
    tf = InputTransform(0.5, 0.25, 10.0, 20.0)
    img = np.array([[100.0, 200.0, 300.0, 400.0]])
    fwd = img * [tf.sx, tf.sy, tf.sx, tf.sy] + [tf.pad_x, tf.pad_y, tf.pad_x, tf.pad_y]
    np.testing.assert_allclose(tf.to_image(fwd), img)


def test_default_model_path_names_the_build_script_or_rejects_unknown_kinds(tmp_path, monkeypatch):
    monkeypatch.setattr("perception.detector.MODELS_DIR", tmp_path)
    with pytest.raises(FileNotFoundError, match="build_detector"):
        default_model_path("centernet")
    with pytest.raises(ValueError, match="unknown detector kind"):
        default_model_path("ssd")


class FakeYoloSession:
    """Stands in for onnxruntime: an ultralytics-style model with input [1,3,320,320] and two classes."""

    def __init__(self, path: str, options: object, providers: list[str]) -> None:
        self.out = np.zeros((1, 6, 100), np.float32)
        self.out[0, :, 5] = [160, 160, 80, 40, 0.0, 0.8]  # "mug" at the centre
        self.out[0, :, 6] = [165, 160, 80, 40, 0.0, 0.7]  # its duplicate
        self.out[0, :, 7] = [40, 170, 20, 20, 0.6, 0.0]  # "robot"
        self.fed: np.ndarray | None = None

    def get_inputs(self) -> list[SimpleNamespace]:
        return [SimpleNamespace(name="images", shape=[1, 3, 320, 320])]

    def get_outputs(self) -> list[SimpleNamespace]:
        return [SimpleNamespace(name="output0", shape=[1, 6, 100])]

    def get_modelmeta(self) -> SimpleNamespace:
        return SimpleNamespace(custom_metadata_map={"names": "{0: 'robot', 1: 'mug'}"})

    def run(self, names: list[str] | None, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        self.fed = feed["images"]
        return [self.out]


def test_yolo_pipeline_reads_names_letterboxes_with_grey_and_maps_boxes_back(monkeypatch):
    monkeypatch.setattr(onnxruntime, "InferenceSession", FakeYoloSession)
    detector = Detector(DetectorSettings(model=Path("fake.onnx"), kind="yolo"))
    assert detector.input_size == 320 and detector.class_names == ("robot", "mug")
    dets = detector.detect(np.zeros((240, 320, 3), np.uint8))  # scale 1, 40 grey rows above and below
    fed = detector.session.fed
    assert fed.shape == (1, 3, 320, 320) and fed[0, 0, 0, 0] == pytest.approx(114 / 255) and fed[0, 0, 100, 0] == 0
    assert [(d.label, round(d.score, 2)) for d in dets] == [("mug", 0.8), ("robot", 0.6)]
    np.testing.assert_allclose([dets[0].box, dets[1].box], [[120, 100, 200, 140], [30, 120, 50, 140]])


# --- regression on real photos ------------------------------------------------------------------


@pytest.fixture(scope="module")
def centernet() -> Detector:
    return Detector(DetectorSettings(kind="centernet"))


@pytest.fixture(scope="module")
def nanodet() -> Detector:
    return Detector(DetectorSettings(kind="nanodet"))


def assert_top(dets: list[Detection], label: str, truth: tuple[float, ...], min_score: float = 0.4) -> None:
    assert dets, f"expected a {label}, got nothing"
    top = dets[0]
    cx, cy = (top.box[0] + top.box[2]) / 2, (top.box[1] + top.box[3]) / 2
    assert (top.label, top.score >= min_score) == (label, True), dets[:3]
    assert truth[0] <= cx <= truth[2] and truth[1] <= cy <= truth[3], top
    assert iou(top.box, truth) >= 0.5, (top, truth)


@pytest.mark.parametrize(
    "image, label, truth",
    [
        (data.chelsea, "cat", CAT_CHELSEA),
        (data.coffee, "cup", CUP_COFFEE),
        (data.astronaut, "person", PERSON_ASTRONAUT),
        (lambda: data.stereo_motorcycle()[0], "motorcycle", MOTORCYCLE),
        (grace_hopper, "person", PERSON_HOPPER),
    ],
    ids=["cat-chelsea", "cup-coffee", "person-astronaut", "motorcycle", "person-grace-hopper"],
)
def test_centernet_finds_the_object_of_each_photo(centernet, image, label, truth):
    dets = centernet.detect(image())
    assert_top(dets, label, truth)
    assert all(isinstance(d.box[0], float) and 0.0 <= d.box[0] < d.box[2] for d in dets)
    assert centernet.last_ms > 0.0


def test_centernet_cup_box_is_tight(centernet):
    assert iou(centernet.detect(data.coffee())[0].box, CUP_COFFEE) >= 0.75


def test_centernet_reports_nothing_confident_on_the_rocket(centernet):
    assert [d for d in centernet.detect(data.rocket()) if d.score >= 0.4] == []


def test_fitted_height_follows_the_aspect_in_multiples_of_32():
    assert [fitted_height(w, h, 512) for w, h in ((640, 480), (512, 512), (600, 400), (480, 640), (1280, 720))] == [
        384,
        512,
        352,
        512,
        288,
    ]


def test_letterbox_into_a_wide_canvas_centres_and_inverts():
    img, tf = letterbox(np.full((300, 640, 3), 7, np.uint8), 512, 0, 288)
    assert img.shape == (288, 512, 3) and img[0, 0, 0] == 0 and img[144, 256, 0] == 7
    np.testing.assert_allclose(
        tf.to_image(np.array([[tf.pad_x, tf.pad_y, 512 - tf.pad_x, 288 - tf.pad_y]])), [[0, 0, 640, 300]], atol=1
    )


def test_centernet_on_a_4_3_image_runs_512_x_384_and_finds_what_the_square_input_finds(centernet):
    image = data.astronaut()[64:448]  # 512 x 384
    fit = Detector(DetectorSettings(kind="centernet", fit_aspect=True))
    assert fit.preprocess(image)[0].shape == (1, 384, 512, 3)
    assert centernet.preprocess(image)[0].shape == (1, 512, 512, 3)
    fitted, full = fit.detect(image), centernet.detect(image)
    assert fitted and fitted[0].label == full[0].label == "person"
    assert iou(fitted[0].box, full[0].box) >= 0.9 and abs(fitted[0].score - full[0].score) < 0.05


def test_reshaping_rejects_bad_heights_and_other_models():
    with pytest.raises(ReshapeError, match="multiple of 32"):
        reshaped_centernet(default_model_path("centernet"), 380)
    with pytest.raises(ReshapeError):
        reshaped_centernet(default_model_path("nanodet"), 384)


def test_nanodet_finds_the_cat_and_the_astronaut(nanodet):
    cats = [d for d in nanodet.detect(data.chelsea()) if d.label == "cat"]
    assert cats and iou(cats[0].box, CAT_CHELSEA) >= 0.5
    assert_top(nanodet.detect(data.astronaut()), "person", PERSON_ASTRONAUT)


def test_allow_list_and_class_thresholds_filter_labels():
    image = data.coffee()
    only_cups = Detector(DetectorSettings(classes=("cup",), score_threshold=0.1)).detect(image)
    assert only_cups and {d.label for d in only_cups} == {"cup"}
    strict = Detector(DetectorSettings(score_threshold=0.1, class_thresholds={"cup": 0.99})).detect(image)
    assert strict and "cup" not in {d.label for d in strict}


def test_coco_names_are_the_standard_80():
    assert len(COCO_CLASSES) == 80 and len(set(COCO_CLASSES)) == 80
    assert (COCO_CLASSES[0], COCO_CLASSES[41], COCO_CLASSES[56], COCO_CLASSES[62], COCO_CLASSES[79]) == (
        "person",
        "cup",
        "chair",
        "tv",
        "toothbrush",
    )


def test_shipped_models_are_present():
    for kind in ("centernet", "nanodet"):
        assert default_model_path(kind).stat().st_size > 5_000_000
    assert Path(default_model_path("centernet")).parent.name == "models"


def test_default_thresholds_depend_on_the_model_and_an_explicit_dict_replaces_them():
    floor, per_class = DetectorSettings().thresholds()
    assert floor == 0.3 and per_class["tv"] > floor > per_class["chair"]
    assert DetectorSettings(kind="nanodet").thresholds()[0] == 0.35
    assert DetectorSettings(kind="yolo", score_threshold=0.5, class_thresholds={}).thresholds() == (0.5, {})


def test_bench_counts_classes_and_writes_a_table_and_contact_sheets(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = "synthetic:room?seed=0&frames=4&width=320&height=240"
    result = run_detector_bench(Console(file=io.StringIO()), spec, 2, tmp_path / "bench.md")
    assert [m["kind"] for m in result["models"]] == ["centernet", "nanodet", "centernet"]
    assert result["models"][2]["model"] == "centernet (fit_aspect: 512 x 384 input for 4:3)"
    assert all(m["frames"] == 2 and m["p50_ms"] > 0 for m in result["models"])
    assert "<!-- bench:detector -->" in (tmp_path / "bench.md").read_text()
    sheet = cv2.imread(str(tmp_path / "docs" / "detector_contact_sheet.jpg"))
    assert sheet.shape == (240, 5 * 320, 3)  # two tiles in the first row of the 4 x 5 grid
    assert (tmp_path / "docs" / "detector_contact_sheet_nanodet.jpg").is_file()


def test_detector_rejects_unknown_kinds_and_non_rgb_images(centernet):
    with pytest.raises(ValidationError, match="centernet"):
        DetectorSettings(kind="ssd")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown detector kind"):
        Detector(DetectorSettings.model_construct(kind="ssd"))
    with pytest.raises(ValueError, match="HxWx3"):
        centernet.detect(np.zeros((48, 64), np.uint8))
