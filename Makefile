# torchrl_causal: two commands do all the set-up on a fresh machine.
#   make train  -> creates .venv, installs, runs the default recipe, writes plots and tables
#   make test   -> creates .venv, installs, runs the test suite
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
export YOLO_OFFLINE ?= 1
export YOLO_CONFIG_DIR ?= $(CURDIR)/.yolo_config
PYTEST_WORKERS ?= 2

.PHONY: venv train test docs bench bench-learning bench-gridnav generalist ship-thesis demo depth-weights detector-weights arrival-weights arrival-rooms-weights arrival-view-weights protocol protocol-status clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# ultralytics needs torchvision; the CPU torch file on disk cannot load PyPI's
	# torchvision, so torch and torchvision are installed as a matched pair first.
	$(PIP) install -q "torch==2.14.1" "torchvision==0.29.1"
	$(PIP) install -q -e ".[dev,perception]"
	touch $@

venv: $(VENV)/.installed

# make train: the default recipe (CBN-DQN V2, default preset) with a budget that fits
# 15 minutes on 2 CPU cores; it ends by printing the policy's greedy success.
TRAIN_ARGS ?= collector.total_frames=12000
train: venv
	$(PY) recipes/train.py $(TRAIN_ARGS)

# make generalist: the policy that flies layouts it has never seen (recipes/config/generalist.yaml:
# oracle teacher phase + DQN phase across random training-split layouts, selected on a validation
# set of training-split layouts), then shipped as torchrl_causal.pretrained "generalist".
# the shipped generalist is seed 1 of 5 (chosen on its validation success, docs/results.rst),
# shipped with a LoopGuard, EgoMap flank_margin 0.3 m, the layout's geofence in the mask and a
# RevisitGuard (each measured on validation, then held-out layouts, docs/results.rst)
GENERALIST_ARGS ?= seed=1
generalist: venv
	$(PY) recipes/train.py --config-name generalist output_dir=outputs/generalist threads=1 \
	    progress=false $(GENERALIST_ARGS)
	$(PY) recipes/ship_policy.py outputs/generalist generalist --loop-guard --flank-margin 0.3 \
	    --geofence env --revisit-guard \
	    --command "make generalist GENERALIST_ARGS='$(GENERALIST_ARGS)'"

# make protocol: the thesis protocol in full (docs/results.rst, "The thesis protocol"), in
# the order the grid runs it: the five variants and the two controls x 5 seeds, the k sweep
# x 5 seeds, then preset=thesis (the five variants x 2 seeds). Every run checkpoints, so the
# same command continues an interrupted grid. Days on 2 cores; PROTOCOL_ARGS picks the
# launcher, e.g. PROTOCOL_ARGS='--launcher ray --jobs 16' on a 16-core box.
PROTOCOL_ARGS ?= --launcher ray --jobs 2
PROTOCOL_RUN := recipes/reproduce.py --mode full --no-estimate $(PROTOCOL_ARGS)
protocol: venv
	$(PY) $(PROTOCOL_RUN) --seeds 5 --root outputs/reproduce --groups variants \
	    -- threads=1 progress=false
	$(PY) $(PROTOCOL_RUN) --seeds 5 --root outputs/reproduce --groups k_sweep \
	    -- threads=1 progress=false
	$(PY) $(PROTOCOL_RUN) --seeds 2 --root outputs/reproduce_thesis --groups variants \
	    --variants dqn_image cbn_defined cbn_p cbn_pn cbn_v2 -- preset=thesis threads=1 progress=false

# make protocol-status: where each run of `make protocol` stands (reproduce.py --status);
# trains nothing
protocol-status: venv
	$(PY) recipes/reproduce.py --mode full --seeds 5 --root outputs/reproduce --status
	$(PY) recipes/reproduce.py --mode full --seeds 2 --root outputs/reproduce_thesis \
	    --groups variants --variants dqn_image cbn_defined cbn_p cbn_pn cbn_v2 --status

# make ship-thesis THESIS_RUN=<run folder of make train>: ship it as pretrained "thesis"
THESIS_RUN ?= outputs/make_train
ship-thesis: venv
	$(PY) recipes/ship_policy.py $(THESIS_RUN) thesis --command "make train"

# make arrival-weights: the shipped arrival head (about 11 minutes on one core): 6,000 frames
# near the thesis board through the Tello camera path, half of them near the goal sphere, 30
# epochs; its test figures go into the weights and arrival.json (docs/tello.rst, "A learned
# arrival head"; fly_tello.py --arrival-head shipped --reach-offset 0.2)
arrival-weights: venv
	$(PY) recipes/train_arrival.py --out torchrl_causal/perception/weights/arrival.pt \
	    --train 6000 --test 600 --epochs 30 --threads 1 --no-progress

# make arrival-rooms-weights: the shipped arrival head for rooms nobody trained on (about 14
# minutes on one core): 6,000 frames in random layouts' rooms of the training split with the
# printed 1.0 x 0.8 m board, tested on 600 frames of held-out rooms beside the thesis-room head;
# fly_tello.py flies it by default on the emulator's random layouts and on a real drone
# (--arrival-head rooms --reach-offset 0.13; docs/tello.rst, "The random-rooms head, shipped")
arrival-rooms-weights: venv
	$(PY) recipes/train_arrival.py --out torchrl_causal/perception/weights/arrival_rooms.pt \
	    --rooms random --train 6000 --test 600 --epochs 30 --threads 1 --no-progress --seed 1 \
	    --compare shipped

# make arrival-view-weights: the arrival head that can decline (about 35 minutes on one core):
# 9,000 frames in random layouts' rooms of the training split with the printed board, the
# camera turned up to 80 deg off facing it and up to 1.2 m beside the goal point (many frames
# without the board), a network of width 32 with an in-view output, 40 epochs; tested on 900
# frames of held-out rooms beside the random-rooms head (fly_tello.py --arrival-head view
# --reach-offset 0.13, asked with --lost-board ask; docs/tello.rst, "A head that can decline")
arrival-view-weights: venv
	$(PY) recipes/train_arrival.py --out torchrl_causal/perception/weights/arrival_view.pt \
	    --rooms random --train 9000 --test 900 --epochs 40 --width 32 --near-share 0.35 \
	    --yaw-deg 80 --lateral 1.2 --ahead-max 1.0 --in-view-share 0.05 --threads 1 \
	    --no-progress --seed 1 --compare torchrl_causal/perception/weights/arrival_rooms.pt

# make detector-weights: the shipped YOLOv8n goal detector (about 2 hours on one core): the
# base network on plain renders (16 epochs), then 6 epochs continued on four datasets rendered
# through the Tello camera path -- the usual mix and close-ups, at 240x320 and at 84x84 -- then
# 4 more epochs with obstacle close-ups added as hard negatives, each stage with its score
# calibrations refitted (docs/perception.rst, "Frames through the Tello's camera path" and
# "Hard negatives"). The shipped sidecar records the last stage's commands and, nested as
# init_sidecar, each earlier stage's own sidecar.
detector-weights: venv
	$(PY) recipes/train_detector.py --data outputs/det_data --epochs 16 --imgsz 256 --batch 16 \
	    --threads 1 --name goal_yolov8n_base --out outputs/det_base/goal_yolov8n.pt
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/mix --video-path --no-progress \
	    --image-size 240 320 --n-train 1000 --n-val 150 --n-test 200 --seed 21
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/close --video-path --no-progress \
	    --image-size 240 320 --n-train 600 --n-val 100 --n-test 120 --seed 22 \
	    --goal-distance 0.25 1.2 --goal-absent-frac 0.1 --start-frac 0
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/mix84 --video-path --no-progress \
	    --image-size 84 84 --n-train 600 --n-val 100 --n-test 200 --seed 23
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/close84 --video-path --no-progress \
	    --image-size 84 84 --n-train 400 --n-val 60 --n-test 120 --seed 24 \
	    --goal-distance 0.25 1.2 --goal-absent-frac 0.1 --start-frac 0
	$(PY) recipes/train_detector.py --data outputs/det_vp/mix --extra-data outputs/det_vp/close \
	    --extra-data outputs/det_vp/mix84 --extra-data outputs/det_vp/close84 \
	    --init outputs/det_base/goal_yolov8n.pt --epochs 6 --imgsz 256 --threads 1 \
	    --warmup-epochs 0 --close-mosaic 2 --name goal_yolov8n_vp --bench-reps 2 \
	    --out outputs/det_vp/ft/goal_yolov8n.pt
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/obst --video-path --no-progress \
	    --image-size 240 320 --n-train 500 --n-val 80 --n-test 200 --seed 25 \
	    --goal-absent-frac 0 --obstacle-frac 1 --obstacle-distance 0.25 1.5
	$(PY) -m torchrl_causal.perception.dataset --out outputs/det_vp/obst84 --video-path --no-progress \
	    --image-size 84 84 --n-train 400 --n-val 60 --n-test 200 --seed 26 \
	    --goal-absent-frac 0 --obstacle-frac 1 --obstacle-distance 0.25 1.5
	$(PY) recipes/train_detector.py --data outputs/det_vp/mix --extra-data outputs/det_vp/close \
	    --extra-data outputs/det_vp/mix84 --extra-data outputs/det_vp/close84 \
	    --extra-data outputs/det_vp/obst --extra-data outputs/det_vp/obst84 \
	    --init outputs/det_vp/ft/goal_yolov8n.pt --epochs 4 --imgsz 256 --threads 1 \
	    --warmup-epochs 0 --close-mosaic 2 --name goal_yolov8n_hn --bench-reps 2

# make depth-weights: the shipped MonoDepth (7.7 M parameters, docs/perception.rst, "The shipped
# weights"): three camera-path data sets (video frames, board close-ups and obstacle close-ups
# through the Tello's H.264 path), then 100 epochs of log-BerHu training from scratch on the first
# two, on the GPU when there is one (about 6 minutes on an H200; about 5 hours on one CPU core),
# then a 6-epoch fine-tune on all three (about 14 minutes on two CPU cores; docs/perception.rst,
# "Obstacle close-ups in training"), each with the arrival rule's range calibrated and stored with
# the weights. DEPTH_DEVICE=cpu|cuda overrides the choice. The first stage of the shipped file was
# trained on an H200 from a working-resolution cache of the same data (benchmarks/gpu_depth/; its
# sidecar says how), the fine-tune on the CPU.
DEPTH_DEVICE ?= $(shell $(PY) -c "import torch; print('cuda' if torch.cuda.is_available() else 'cpu')" 2>/dev/null || echo cpu)
depth-weights: venv
	$(PY) -m torchrl_causal.perception.dataset --out outputs/depth_vp --n-train 2000 \
	    --n-val 200 --n-test 200 --seed 12 --video-path --no-progress
	$(PY) -m torchrl_causal.perception.dataset --out outputs/depth_close --n-train 2000 \
	    --n-val 200 --n-test 200 --seed 11 --goal-absent-frac 0 --start-frac 0 \
	    --goal-distance 0.25 1.5 --video-path --no-progress
	$(PY) -m torchrl_causal.perception.dataset --out outputs/depth_obst --n-train 2000 \
	    --n-val 200 --n-test 200 --seed 21 --goal-absent-frac 0 --obstacle-frac 1.0 \
	    --video-path --no-progress
	$(PY) recipes/train_depth.py --data outputs/depth_vp outputs/depth_close --loss log-berhu \
	    --epochs 100 --lr 3e-3 --batch-size 32 --widths 32 64 96 160 224 --decoder 160 96 64 32 \
	    --device $(DEPTH_DEVICE) --threads 1 --run-dir outputs/depth_run \
	    --out outputs/depth_base.pt --no-progress
	$(PY) recipes/train_depth.py --data outputs/depth_vp outputs/depth_close outputs/depth_obst \
	    --init outputs/depth_base.pt --loss log-berhu --epochs 6 --lr 5e-4 --batch-size 16 \
	    --device $(DEPTH_DEVICE) --threads 2 --run-dir outputs/depth_run_obst --no-progress

# make demo: watch the shipped policies fly (recipes/watch.py): flight.mp4 (onboard camera +
# chase view), flight_maps.png and episodes.jsonl, thesis on the thesis scene and generalist
# on held-out layouts, in outputs/demo/<policy>
demo: venv
	$(PY) recipes/watch.py --policy thesis --layout thesis --episodes 2 \
	    --out outputs/demo/thesis --overwrite
	$(PY) recipes/watch.py --policy generalist --layout heldout --episodes 4 \
	    --out outputs/demo/generalist --overwrite

test: venv
	$(PY) -m pytest -n $(PYTEST_WORKERS) --durations=15 --doctest-modules torchrl_causal tests

docs: venv
	$(PY) -m sphinx -W --keep-going -b html docs docs/_build/html

# the speed benchmarks (minutes); the learning benchmarks train many runs:
# make bench-learning (drone, hours) and make bench-gridnav (grid world, ~20 min)
LEARNING_BENCHES := benchmarks/learning.py benchmarks/gridnav.py benchmarks/generalisation.py
bench: venv
	for b in $(filter-out $(LEARNING_BENCHES),$(wildcard benchmarks/*.py)); do $(PY) $$b || exit 1; done

bench-learning: venv
	$(PY) benchmarks/learning.py

bench-gridnav: venv
	$(PY) benchmarks/gridnav.py --plot docs/_static/results/gridnav_success.png

clean:
	rm -rf $(VENV) docs/_build outputs .pytest_cache
