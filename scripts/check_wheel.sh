#!/usr/bin/env bash
# Installs trapflow the way the Docker images and most users do (a wheel, not editable),
# into a fresh venv outside the source tree, checks that every run-time file is inside the
# wheel, then runs the README's quick start from an empty folder.
# Usage: scripts/check_wheel.sh [DURATION_S]
set -euo pipefail
src=$(cd "$(dirname "$0")/.." && pwd)
duration=${1:-5}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# From a copy of the tracked and unignored files: a stale build/ folder in the checkout
# would put modules in the wheel that the tree no longer has.
mkdir "$work/src"
(cd "$src" && git ls-files -z --cached --others --exclude-standard | tar -c --null -T - -f -) \
  | tar -x -C "$work/src"
# setuptools' warnings of a data folder it will stop installing ("is absent") fail it now
# (pip shows the build's own output only with -v).
python3 -m pip wheel -v --no-deps --wheel-dir "$work/dist" "$work/src" > "$work/build.log" 2>&1 \
  || { cat "$work/build.log"; exit 1; }
if grep -E "as data is deprecated|Package '.*' is absent" "$work/build.log"; then
  echo "the build warns of data folders that are not packages (setup.py)" >&2
  exit 1
fi
wheel=$(ls "$work"/dist/trapflow-*.whl)
python3 - "$wheel" <<'PY'
import sys, zipfile
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
needed = [
    "trapflow/py.typed",
    "trapflow/viewer/static/index.html",
    "trapflow/viewer/static/viewer.js",
    "trapflow/viewer/static/viewer.css",
    "trapflow_workers/models/crab_detector.onnx",
    "trapflow_workers/models/crab_detector_int8.onnx",
    "trapflow_workers/models/crab_detector.labels",
    "trapflow_workers/models/scene_classifier.onnx",
    "trapflow_workers/models/scene_classifier.labels",
]
missing = [n for n in needed if n not in names]
if missing:
    sys.exit(f"wheel lacks run-time files: {missing}")
print(f"wheel holds {len(names)} files, all {len(needed)} run-time files among them")
PY
python3 -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --upgrade pip
"$work/venv/bin/python" -m pip install --quiet "$wheel"
cd "$work"
# Every module imports from the installed copy (not the source tree, which is not on the path).
"$work/venv/bin/python" - <<'PY'
import importlib, pkgutil, trapflow, trapflow_workers
for pkg in (trapflow, trapflow_workers):
    for mod in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
        if mod.name.endswith(("picamera2", "__main__")):
            continue  # the Pi's camera stack; the command line itself
        importlib.import_module(mod.name)
assert "site-packages" in trapflow.__file__, trapflow.__file__
print("every module imports from", trapflow.__file__)
PY
"$work/venv/bin/trapflow" start --workers mono=1,stereo=1,vo=1 --duration "$duration"
test -s "$work"/runs/latest/results.jsonl
echo "quick start from the wheel: $(wc -l < "$work"/runs/latest/results.jsonl) result lines"
