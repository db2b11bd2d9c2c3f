#!/usr/bin/env bash
# iSAM2 growth with the pinned gtsam 4.3.0 and with gtsam 4.2.2, each in a throwaway venv (see the .py).
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
for spec in "gtsam==4.3.0 numpy==2.4.6 scipy==1.17.1" "gtsam==4.2.2 numpy==1.26.4 scipy==1.13.1"; do
  python3 -m venv "$work/venv"
  "$work/venv/bin/pip" install -q $spec rich==15.0.0
  (cd "$here" && PYTHONPATH="$here" "$work/venv/bin/python" scripts/isam2_gtsam_versions.py 10000 --service)
  rm -rf "$work/venv"
done
