# `make test` and `make demo` set everything up on a fresh machine (Python >= 3.10 with venv).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO ?= demo
# The CPU wheel of torch; any other spec would pull several GB of CUDA packages.
TORCH_SPEC ?= torch==2.13.0

.PHONY: install test demo bench clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet "$(TORCH_SPEC)"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@

test: install
	$(BIN)/python -m pytest

# The sample subject through the whole loop (grows as the refinement stages land).
demo: install
	$(BIN)/avatarperfect make-sample $(DEMO)/sample
	$(BIN)/avatarperfect train-initial $(DEMO)/sample/train $(DEMO)/ws --force
	$(BIN)/avatarperfect evaluate $(DEMO)/ws --test $(DEMO)/sample/test
	$(BIN)/avatarperfect render $(DEMO)/ws --motion examples/motions/walk.npz -o $(DEMO)/walk.mp4

bench: install
	$(BIN)/python benchmarks/rasterizer.py

clean:
	rm -rf $(VENV) $(DEMO)
