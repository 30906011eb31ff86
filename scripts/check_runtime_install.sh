#!/usr/bin/env bash
# The torch-free deployment path, checked for real (export issue): install nehad WITHOUT the
# training extra into a new virtual environment, confirm torch is absent there, and render an
# exported model.onnx with it; the image must equal the one rendered in the full environment.
#
#   bash scripts/check_runtime_install.sh [WORKDIR]
#
# Needs the full (training) environment on PATH as `python` to make the model. The venv reuses
# pip's cache, so a second run is much faster than the first.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
work="${1:-$(mktemp -d)}"
mkdir -p "$work"
start=$(date +%s)

echo "== model: a tiny synthetic scene, trained (test preset) and exported, in the full environment"
python -m nehad.cli.main synth "$work/scene" --resolution 32 --frames 8 --gaussians 0 >/dev/null
python -m nehad.cli.main train "$work/scene" -o "$work/run" --preset test --quiet >/dev/null
python -m nehad.cli.main export "$work/run" -o "$work/model.onnx" >/dev/null
python -m nehad.cli.main render "$work/model.onnx" --view "$work/scene/transforms_test.json:0" \
    --time 0.5 -o "$work/full.png" >/dev/null

echo "== venv: pip install $repo (base install, no extras)"
t0=$(date +%s)
python -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$repo"
t1=$(date +%s)
echo "   install took $((t1 - t0)) s"

echo "== torch must be absent in the venv"
if "$work/venv/bin/python" -c "import torch" 2>/dev/null; then
    echo "FAILED: torch is importable in the runtime-only venv" >&2
    exit 1
fi

echo "== render model.onnx in the venv"
"$work/venv/bin/nehad" render "$work/model.onnx" --view "$work/scene/transforms_test.json:0" \
    --time 0.5 -o "$work/venv.png"
# sed, not head: head would close the pipe early and the SIGPIPE fails the script under pipefail
"$work/venv/bin/nehad" info "$work/model.onnx" | sed -n 1,3p
# run from $work: in the repository root the source folder nehad/ would shadow the installed package
(cd "$work" && "$work/venv/bin/python" - "$work/full.png" "$work/venv.png") <<'PY'
import sys
import numpy as np
from nehad.runtime.images import read_image
a, b = read_image(sys.argv[1]), read_image(sys.argv[2])
diff = float(np.abs(a - b).max())
print(f"   max |full - venv| = {diff:.3g}")
sys.exit(0 if diff <= 1 / 255 else 1)
PY
echo "OK: runtime-only install renders model.onnx without torch ($(( $(date +%s) - start )) s in all)"
