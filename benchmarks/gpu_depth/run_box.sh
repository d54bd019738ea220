#!/usr/bin/env bash
# MonoDepth trainings side by side on one GPU box, from a working-resolution cache:
#
#   bash benchmarks/gpu_depth/run_box.sh OUT SECONDS CACHE RUNS_FILE
#
# RUNS_FILE has one run per line, "NAME <train_depth.py options>" (e.g.
# "wider_b32 --epochs 100 --lr 3e-3 --batch-size 32 --widths 32 64 96 160 224 --decoder 160 96 64 32").
# Every run gets the common options below (the two camera-path sets, log BerHu,
# --device cuda); all start at once and each stops after SECONDS. A run that finished
# leaves its weights (OUT/NAME.pt); a run cut off leaves its best epoch so far, from its
# checkpoint. The logs, sidecars and histories go to OUT/logs.tgz (the device tool
# brings back at most 8 files).
set -u
OUT=$1; SECS=$2; CACHE=$3; RUNS=$4
cd "$(dirname "$0")/../.."
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
COMMON="--data ${DATA:-depth_vp depth_close} --loss log-berhu --device ${DEVICE:-cuda} --threads 2 --n-test-84 0 --reach-poses 0 --no-progress"
mkdir -p /tmp/gd/logs /tmp/gd/w /tmp/gd/runs
NAMES=()
while read -r name opts; do
  [ -z "$name" ] && continue
  NAMES+=("$name")
  # shellcheck disable=SC2086
  (timeout --signal=INT "$SECS" python3 benchmarks/gpu_depth/train_cached.py --cache "$CACHE" -- $COMMON \
      --run-dir /tmp/gd/runs/$name --out /tmp/gd/w/$name.pt $opts > /tmp/gd/logs/$name.log 2>&1;
   echo "$name rc=$?") &
done < "$RUNS"
wait
python3 - "$OUT" "${NAMES[@]}" <<'PY'
import json, sys
from pathlib import Path
import torch
from torchrl_causal.perception.depth import FCRN, MonoDepth
out, names = Path(sys.argv[1]), sys.argv[2:]
for n in names:
    w, ck = Path(f"/tmp/gd/w/{n}.pt"), Path(f"/tmp/gd/runs/{n}/last.pt")
    if w.is_file():
        (out / f"{n}.pt").write_bytes(w.read_bytes())
        Path(f"/tmp/gd/logs/{n}.json").write_text(w.with_suffix(".json").read_text())
        print(n, "finished")
    elif ck.is_file():
        c = torch.load(ck, map_location="cpu", weights_only=False)
        a, st = c["args"], c["state"]
        net = (MonoDepth.load(a["init"]).net.float() if a["init"] else
               FCRN(widths=tuple(a["widths"]), decoder=tuple(a["decoder"])))
        net.load_state_dict(st["best_state"])
        rec = {"cut_off_after_epoch": st["epoch"], "args": a, "best": st["best"]}
        MonoDepth(net, work_height=a["work_height"]).save(out / f"{n}.pt", meta=rec)
        Path(f"/tmp/gd/logs/{n}.json").write_text(json.dumps({**rec, "history": st["history"]}, indent=1))
        print(n, "cut off after epoch", st["epoch"], "best", st["best"])
    else:
        print(n, "nothing")
PY
tar czf "$OUT/logs.tgz" -C /tmp/gd logs
ls -la "$OUT"
