#!/usr/bin/env bash
# The GPU checks of a CUDA machine in one go (docs/recipes.rst, "On a GPU"):
#
#   bash benchmarks/gpu_box.sh OUT_DIR [TOTAL_SECONDS]
#
# 1. versions, the GPU, one rendered frame (MUJOCO_GL=egl renders on the GPU);
# 2. the CUDA tests (tests/test_gpu.py);
# 3. benchmarks/training.py with device=cuda, then on one CPU thread of the same box,
#    back to back (one JSON object per figure in OUT_DIR/bench_<device>.jsonl);
# 4. with TOTAL_SECONDS > 0: the thesis protocol's variant grid (recipes/reproduce.py
#    --mode full --groups variants, 700 episodes a run, seed-major, device=cuda, one job per
#    core but one) until TOTAL_SECONDS after the start, less 45 s to pack; the runs that
#    finished are packed into OUT_DIR/grid.tgz (without checkpoints), and
#    OUT_DIR/protocol.json says how many runs finished in how long on how many jobs, and how
#    far the others got (episodes, frames).
#
# Stages 2-4 each run under their own time limit, and one failing does not stop the next.
#
# Environment knobs (defaults in brackets):
#   STAGES       which stages run [1234]
#   GRID_DEVICE  device of the grid's runs [cuda]; cpu runs one job per core on the CPUs
#   GRID_PARTS   ';'-separated reproduce.py selections launched side by side into one root,
#                each with its own --jobs [--groups variants --jobs <cores - 1>], e.g.
#                "--variants cbn_defined --jobs 3;--groups k_sweep --jobs 4"; a part may end
#                with its own hydra overrides ("... --jobs 1 -- env.max_steps=30")
#   GRID_RECORDS a folder of finished runs' records (reproduce.py --export) copied into the
#                root first, so those runs are not trained again [none]
set -u
OUT=${1:?usage: bash benchmarks/gpu_box.sh OUT_DIR [TOTAL_SECONDS]}
TOTAL=${2:-0}
PY=${PYTHON:-python3}
ROOT=${GRID_ROOT:-/tmp/gpu_box_grid}
STAGES=${STAGES:-1234}
GRID_DEVICE=${GRID_DEVICE:-cuda}
mkdir -p "$OUT"
export MUJOCO_GL=${MUJOCO_GL:-egl} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} PYTHONUNBUFFERED=1
T0=$(date +%s)
stage() { echo "=== $1 (t=$(( $(date +%s) - T0 )) s)"; }

if [[ $STAGES == *1* ]]; then
stage "1 environment"
nvidia-smi -L || { echo "no NVIDIA GPU"; exit 1; }
$PY - <<'EOF' || { echo "stage 1 failed: the project does not import or render here"; exit 1; }
import platform
import mujoco, pgmpy, tensordict, torch, torchrl
from torchrl_causal.envs import DroneNavEnv
print(f"python {platform.python_version()} torch {torch.__version__} torchrl {torchrl.__version__} "
      f"tensordict {tensordict.__version__} mujoco {mujoco.__version__} pgmpy {pgmpy.__version__}")
print("cuda:", torch.cuda.is_available(), torch.cuda.get_device_name(0))
env = DroneNavEnv(seed=0)
td = env.reset()
print("rendered", tuple(td["pixels"].shape), "mean", float(td["pixels"].float().mean()))
env.close()
EOF
fi

if [[ $STAGES == *2* ]]; then
stage "2 CUDA tests"
timeout 360 $PY -m pytest -q -p no:cacheprovider tests/test_gpu.py > "$OUT/cuda_tests.txt" 2>&1
echo "cuda tests rc=$?"; tail -3 "$OUT/cuda_tests.txt"
fi

if [[ $STAGES == *3* ]]; then
stage "3 training benchmark, cuda then cpu"
for dev in cuda cpu; do
  timeout 240 $PY benchmarks/training.py --device "$dev" --frames 1000 --ratios 0.25 1 \
      --single-env-only --overlap off --threads 1 > "$OUT/bench_$dev.jsonl" 2> "$OUT/bench_$dev.err"
  echo "bench $dev rc=$?"; cat "$OUT/bench_$dev.jsonl"
done
fi

SECS=$(( TOTAL - 45 - ($(date +%s) - T0) ))
if [[ $STAGES == *4* ]] && [ "$TOTAL" -gt 0 ] && [ "$SECS" -gt 30 ]; then
  stage "4 protocol grid for ${SECS} s on $GRID_DEVICE"
  PARTS=${GRID_PARTS:-"--groups variants --jobs $(( $(nproc) - 1 ))"}
  mkdir -p "$ROOT"
  if [ -n "${GRID_RECORDS:-}" ]; then cp -r "$GRID_RECORDS"/. "$ROOT"/; fi
  touch "$ROOT/.grid_start"  # runs that finish after this were trained here
  JOBS=0
  START=$(date +%s)
  IFS=';' read -ra PART <<< "$PARTS"
  PIDS=()
  for i in "${!PART[@]}"; do
    # shellcheck disable=SC2086
    set -- ${PART[$i]}
    while [ $# -gt 0 ]; do [ "$1" = --jobs ] && JOBS=$(( JOBS + $2 )); shift; done
    # each part in its own process group (setsid), so that what it leaves running (the
    # launcher's worker processes) is stopped below without touching other jobs
    # shellcheck disable=SC2086
    setsid timeout --signal=INT --kill-after=20 "$SECS" $PY recipes/reproduce.py --mode full --seeds 5 \
        --root "$ROOT" --no-estimate ${PART[$i]} \
        -- device="$GRID_DEVICE" threads=1 progress=false outputs.videos=0 \
        > "$OUT/protocol_$i.log" 2>&1 &
    PIDS+=($!)
  done
  RC=0
  for p in "${PIDS[@]}"; do wait "$p" || RC=$?; done
  END=$(date +%s)
  for p in "${PIDS[@]}"; do kill -- -"$p" 2>/dev/null; done
  DONE=$(cd "$ROOT" 2>/dev/null && find . -name summary.json -newer .grid_start -printf '%h\n' | sort)
  N=$(echo "$DONE" | grep -c . )
  echo "protocol rc=$RC: $N runs finished in $(( END - START )) s on $JOBS $GRID_DEVICE jobs"
  if [ "$N" -gt 0 ]; then
    (cd "$ROOT" && tar czf "$OUT/grid.tgz" --exclude=checkpoints --exclude='*.pt' --exclude='*.png' --exclude=videos --exclude=logs $DONE)
  fi
  $PY - "$ROOT" "$OUT/protocol.json" "$(( END - START ))" "$JOBS" "$RC" <<'EOF'
import json, sys
from pathlib import Path
root, out, secs, jobs, rc = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
runs = []
t0 = (root / ".grid_start").stat().st_mtime
for s in sorted(root.rglob("summary.json")):
    if s.stat().st_mtime <= t0:
        continue  # a record copied in from GRID_RECORDS
    d = json.loads(s.read_text())
    wall = s.stat().st_mtime - (s.parent / "config.yaml").stat().st_mtime
    runs.append({"run": str(s.parent.relative_to(root)), "frames": d.get("frames"),
                 "episodes": d.get("episodes"), "loop_s": round(d.get("loop_seconds", 0), 1),
                 "wall_s": round(wall, 1), "peak_rss_mb": d.get("peak_rss_mb")})
started = []
for p in sorted(root.rglob("config.yaml")):
    if p.parent.name == ".hydra" or (p.parent / "summary.json").exists():
        continue
    eps = p.parent / "episodes.csv"
    rows = eps.read_text().splitlines()[1:] if eps.exists() else []
    frames = sum(int(r.split(",")[head.index("length")]) for r in rows) if rows and (
        head := eps.read_text().splitlines()[0].split(",")) and "length" in head else None
    started.append({"run": str(p.parent.relative_to(root)), "episodes": len(rows),
                    "frames": frames, "age_s": round(eps.stat().st_mtime - p.stat().st_mtime, 1)
                    if eps.exists() else None})
print(json.dumps({"figure": "protocol_on_gpu_box", "seconds": secs, "jobs": jobs, "rc": rc,
                  "finished": len(runs), "unfinished": started, "runs": runs}))
Path(out).write_text(json.dumps({"seconds": secs, "jobs": jobs, "rc": rc, "runs": runs,
                                 "started": started}, indent=1))
EOF
fi
stage "done"
