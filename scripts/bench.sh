#!/usr/bin/env bash
# Benchmarks of trapflow on this machine; numbers go to bench-results/ (JSON per part and
# bench.md with everything). Speed is measured here, never asserted in tests.
# Usage: scripts/bench.sh [--quick | --pi | --parts LIST] [OUT_DIR]   (set PYTHON to choose the interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
usage() {
  cat <<'TXT'
Usage: scripts/bench.sh [--quick | --pi | --parts LIST] [--help] [OUT_DIR]   (default OUT_DIR: bench-results)

--pi: the deployment table, run on the device (Raspberry Pi 5, Jetson, any board with
trapflow installed, nothing else running): per algorithm CPU and wall ms per pair at
1280x720 on one core (detector int8 and fp32), the pipeline's parallel overhead per pair
at 10 pairs/s, and the VO floor under saturating recognisers. About 4 minutes on the
2-core development machine (not yet timed on a Pi);
writes OUT_DIR/pi.md and pi.json and prints the table (python -m benchmarks.pi --help
for another size or rate).

Parts, in order, with their run time on a 2-core machine (full / --quick):
  transport   broker path vs raw pyzmq, JPEG and raw pairs        ~3 min  / skipped
  peers       raw pyzmq, trapflow, dora-rs, Eclipse Zenoh, Cyclone
              DDS: 1 -> 1 lossless, 4 in flight, JPEG and raw pairs
              (pip install -e .[peers]; a peer that does not import
              or start is a row saying why)                       ~2 min  / skipped
  remote      remote pools over tcp, with CURVE, vs raw pyzmq     ~1 min  / skipped
  shm, synth  shared-memory ring; synthetic world rendering       ~1 min  / skipped
  cpu         CPU per captured pair by process role at 10 and 15
              pairs/s: default, --encoding raw, --encoding jpeg;
              the part inside process() and the rest              ~5 min  / ~2.5 min
              (6 pipeline runs; about twice as long on a loaded machine)
  floor       VO pairs/s against capture with recognisers burning
              2 s (stereo) and 100 ms (two mono workers) per pair ~1 min  / ~0.5 min
  decode      JPEG encode/decode of one image, OpenCV vs simplejpeg,
              colour, grey, 1/2 scale, 1280x720 and 1920x1080    ~1 min  / ~0.5 min
  vo          stereo VO CPU per pair by stage at 1280x720 against the
              plugin before issue 27 (ratio, same run), and drift of both
              on the conformance scene (--quick: 40 pairs, no drift)
                                                                  ~2 min  / ~0.5 min
  algorithms  decode and process time per algorithm; the detector
              fp32 vs int8, preallocated vs allocating input, JPEG
              decoded whole vs reduced (ratios, same run)          ~3 min  / skipped
  detector    int8 vs fp32 demo detector on 480 held-out synthetic
              pairs, one run: mAP@0.5, recall/precision, process()
              and inference time (int8 is the default while its crab
              mAP is within 0.02 of fp32's)                       ~4 min  / skipped
  process     Dask LocalCluster vs one plain loop                 ~2 min  / skipped
  viewer      live viewer's CPU (viewer + broker beyond a pipeline
              without viewer) with no page open and with one     ~3 min  / skipped
  modem       modem link                                          ~1 min  / skipped
  tracking    trapflow's tracker vs greedy IoU and ByteTrack (trackers, if
              installed) on held-out synthetic sequences, HOTA (TrackEval),
              IDF1 and MOTA (py-motmetrics), full rate and 1 pair in 3;
              the tracker inside live runs of the pipeline, same
              scores, beside the others on the run's detections    ~8 min  / skipped
  measure     stereo range and length against the synthetic truth per range
              bin, honesty of the stated sd, cost per box          ~2 min  / skipped
              track speeds over the ground, rig still and moving,
              VO's poses against the truth (benchmarks/speed.py)   ~5 min  / skipped
  gate        motion gate: cost per pair per method, pairs fed, animals
              missed, empty water withheld; whole pipelines on rendered
              sequences gated vs ungated: recognisers' CPU, CPU per hour,
              days on a Pi 5 battery, animal recall, snow   ~20 min / skipped
  recycle     worker recycling: health check per pair, replacement
              time                                                ~1 min  / skipped

Numbers go to OUT_DIR: one JSON (and Markdown) per part, and OUT_DIR/bench.md with all
of them; the CPU table is what docs/benchmarks.md quotes. Nothing is asserted.
--quick runs the cpu, floor, decode and vo parts only, with short windows.
--parts LIST runs the named parts only, in the order above, in one run (comma-separated:
transport, peers, remote, shm, cpu, decode, vo, algorithms, detector, process, viewer,
modem, tracking, measure, gate, recycle; floor comes with cpu), e.g. --parts
vo,detector,process,transport; bench.md then holds those parts and the load average.
TXT
}
QUICK=0
PARTS=""
ALL_PARTS="transport peers remote shm cpu decode vo algorithms detector process viewer modem tracking measure gate recycle"
while [ $# -gt 0 ]; do
  case "$1" in
    -h|--help) usage; exit 0 ;;
    --quick) QUICK=1; shift ;;
    --pi) QUICK=pi; shift ;;
    --parts)
      PARTS=" ${2:-} "; PARTS=${PARTS//,/ }
      for p in $PARTS; do
        case " $ALL_PARTS " in
          *" $p "*) ;;
          *) echo "scripts/bench.sh: unknown part '$p' in --parts (expected some of:" \
                  "${ALL_PARTS// /,})" >&2; exit 2 ;;
        esac
      done
      [ -n "${PARTS// /}" ] || { echo "scripts/bench.sh: --parts needs a list, e.g." \
                                      "--parts vo,process" >&2; exit 2; }
      shift 2 ;;
    -*) echo "scripts/bench.sh: unknown option $1 (expected --quick, --pi, --parts, --help or OUT_DIR)" >&2
        usage >&2; exit 2 ;;
    *) break ;;
  esac
done
OUT=${1:-bench-results}
PY=${PYTHON:-python}
mkdir -p "$OUT"
if [ "$QUICK" = pi ]; then
  echo "[bench] deployment table on $(uname -m), $(nproc) cores (a few minutes)" >&2
  "$PY" -m benchmarks.pi --out "$OUT"
  exit 0
fi
if [ "$QUICK" = 1 ]; then
  echo "[bench] cpu per pair by role and the VO floor (quick)" >&2
  "$PY" -m benchmarks.cpu --quick --out "$OUT" > /dev/null
  echo "[bench] JPEG decode (quick)" >&2
  "$PY" -m benchmarks.decode --quick --out "$OUT" > /dev/null
  echo "[bench] stereo VO against the plugin before issue 27 (quick)" >&2
  "$PY" -m benchmarks.vo --quick --out "$OUT" > /dev/null
  { echo "# trapflow benchmark (quick), $(date -u '+%Y-%m-%d %H:%M UTC'), $(nproc) cores"
    echo; cat "$OUT/cpu.md"; echo; cat "$OUT/decode.md"; echo; cat "$OUT/vo.md"; } > "$OUT/bench.md"
  echo "[bench] wrote $OUT/bench.md" >&2
  exit 0
fi
# want PART: true when every part runs (no --parts) or PART was named.
want() { [ -z "$PARTS" ] || [[ $PARTS == *" $1 "* ]]; }
# What this run wrote: a part not run leaves nothing behind from an earlier run.
started=$(date +%s)
load_before=$(cut -d' ' -f1-3 /proc/loadavg)
if want transport; then
  echo "[bench] transport (broker path vs raw pyzmq)" >&2
  "$PY" -m benchmarks.transport --out "$OUT" > /dev/null
fi
if want peers; then
  echo "[bench] peers (raw pyzmq, trapflow, dora-rs, Zenoh, Cyclone DDS)" >&2
  "$PY" -m benchmarks.peers --out "$OUT" > /dev/null
fi
if want remote; then
  echo "[bench] remote pools (tcp with CURVE vs raw pyzmq over tcp)" >&2
  "$PY" -m benchmarks.remote --out "$OUT" > /dev/null
fi
if want shm; then
  echo "[bench] shm" >&2
  "$PY" -m benchmarks.shm --out "$OUT" > /dev/null
  echo "[bench] synth" >&2
  "$PY" -m benchmarks.synth --out "$OUT" > /dev/null
fi
if want cpu; then
  echo "[bench] cpu per pair by role and the VO floor" >&2
  "$PY" -m benchmarks.cpu --out "$OUT" > /dev/null
fi
if want decode; then
  echo "[bench] JPEG decode" >&2
  "$PY" -m benchmarks.decode --out "$OUT" > /dev/null
fi
if want vo; then
  echo "[bench] stereo VO against the plugin before issue 27" >&2
  "$PY" -m benchmarks.vo --out "$OUT" > /dev/null
fi
if want algorithms; then
  echo "[bench] algorithms" >&2
  "$PY" -m benchmarks.algorithms --out "$OUT" > /dev/null
fi
if want detector; then
  echo "[bench] detector int8 vs fp32 (time and accuracy, held-out synthetic pairs)" >&2
  "$PY" scripts/quantize_detector.py --eval-only --out "$OUT" > /dev/null
fi
if want process; then
  echo "[bench] process (Dask LocalCluster vs one plain loop)" >&2
  "$PY" -m benchmarks.process --out "$OUT" > /dev/null
fi
if want viewer; then
  echo "[bench] live viewer (no page, a page open, no viewer: 30 s each)" >&2
  "$PY" -m benchmarks.viewer --out "$OUT" > /dev/null
fi
if want modem; then
  echo "[bench] modem link" >&2
  "$PY" -m benchmarks.modem --out "$OUT" > /dev/null
fi
if want tracking; then
  echo "[bench] tracking (held-out synthetic sequences, offline and in live runs)" >&2
  "$PY" -m benchmarks.tracking --live --out "$OUT" > /dev/null
fi
if want measure; then
  echo "[bench] stereo measurement (held-out synthetic sequences)" >&2
  "$PY" -m benchmarks.measure --out "$OUT" > /dev/null
  "$PY" -m benchmarks.speed --out "$OUT" > /dev/null
fi
if want gate; then
  echo "[bench] motion gate" >&2
  "$PY" -m benchmarks.gate --out "$OUT" > /dev/null
fi
if want recycle; then
  echo "[bench] worker recycling (health check per pair, replacement time)" >&2
  "$PY" -m benchmarks.recycle --out "$OUT" > /dev/null
fi
# One section per part run, in the order above; a file older than this run is an earlier
# run's and is left out.
fresh() { [ -f "$1" ] && [ "$(stat -c %Y "$1")" -ge "$started" ]; }
{
  echo "# trapflow benchmark, $(date -u '+%Y-%m-%d %H:%M UTC'), $(nproc) cores"
  echo
  echo "Parts: ${PARTS:-all}; load average before: $load_before, after: $(cut -d' ' -f1-3 /proc/loadavg)"
  echo
  for md in "$OUT"/transport.md "$OUT"/peers.md "$OUT"/remote.md "$OUT"/shm.md "$OUT"/synth.md "$OUT"/cpu.md \
            "$OUT"/decode.md "$OUT"/vo.md "$OUT"/algorithms.md "$OUT"/quantize_detector.md \
            "$OUT"/process.md "$OUT"/viewer.md "$OUT"/modem.md "$OUT"/tracking.md \
            "$OUT"/measure.md "$OUT"/speed.md "$OUT"/gate.md "$OUT"/recycle.md; do
    if fresh "$md"; then cat "$md"; echo; fi
  done
} > "$OUT/bench.md"
echo "[bench] wrote $OUT/bench.md" >&2
