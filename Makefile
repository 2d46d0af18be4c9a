# weathergen: set-up, tests, demo and benchmarks in a local virtual environment.
#
#   make test                  create .venv, install the pinned CPU torch, the package, run the
#                              linter (ruff, configured in pyproject.toml) and the quick tests
#                              (all but those marked slow), in
#                              TEST_WORKERS=2 pytest-xdist processes of one torch thread each
#                              (TEST_WORKERS=0: in one process; PYTEST_ARGS: more pytest options,
#                              e.g. --shuffle-seed N to run them in a shuffled order)
#   make test-slow             the end-to-end tests (marker slow); CI runs make test, then this
#   make demo                  render the default preset on the bundled demo scene
#   make bench                 measure speed and memory (renderer, weather field, combined weather,
#                              the atmosphere, networks, attack step, batched attacks, training,
#                              the README's quick look) and write the figures, with the tree and
#                              machine they were measured on, into docs/figures/bench.md and
#                              bench.json;
#                              FOG_BEFORE=DIR also times fog with the weathergen source tree
#                              DIR (e.g. an older commit's), CORE_BEFORE=DIR the render core
#                              against the renderer of tree DIR
#   make test TORCH=torch      use another torch (e.g. a CUDA build) instead of the pinned CPU one
#   make test-oldest           the tests against the lowest allowed versions (constraints/oldest.txt),
#                              in a separate environment (.venv-oldest)
#   make images                regenerate the pictures of README.md and docs/ (docs/images/) from the
#                              demo scene; REAL=DIR also draws every preset into the first pair of
#                              DIR (REAL_DATASET=kitti, DEPTH_SCALE=...) into out/images/
#   make cli-docs              rewrite docs/cli.md (the command-line reference) from the commands'
#                              --help; a test fails when the two differ
#   make gpu-check             on a machine with CUDA (with TORCH=torch, a CUDA build): every CUDA
#                              test and GPU benchmark, one table; the figures, with the GPU, torch
#                              and tree, go to docs/figures/gpu-check.json and the page
#                              docs/figures/gpu.md (GPU_FIGURES=DIR: into DIR instead);
#                              without CUDA it says so in one line and stops

PYTHON ?= python3
VENV   ?= .venv
TORCH  ?= torch==2.13.0
PYTEST_ARGS ?=
TEST_WORKERS ?= 2
FOG_BEFORE ?=
CORE_BEFORE ?=
REAL ?=
REAL_DATASET ?= kitti
DEPTH_SCALE ?=
GPU_FIGURES ?= docs/figures
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.weathergen-deps
# The torch requirement the venv was last set up with; a different TORCH reinstalls torch.
TORCH_STAMP := $(VENV)/.weathergen-torch

OLDEST ?= .venv-oldest

.PHONY: venv install test test-slow test-oldest demo bench images cli-docs gpu-check clean FORCE

venv: $(STAMP)

# Torch comes first and on its own: an unpinned torch pulled in as a dependency would fetch
# gigabytes of CUDA packages, while the pinned one is a CPU build. The recipe runs every time but
# touches $(TORCH_STAMP) only when TORCH differs from the recorded requirement; a torch already
# installed is then replaced (pip would otherwise call any installed torch "already satisfied").
$(TORCH_STAMP): FORCE
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@if [ "$$(cat $@ 2>/dev/null)" != '$(TORCH)' ]; then \
	    if [ -f $@ ]; then \
	        echo "installing $(TORCH) in place of $$(cat $@)"; \
	        $(BIN)/python -m pip install -q --force-reinstall --no-deps "$(TORCH)" || exit 1; \
	    fi; \
	    echo "installing $(TORCH) into $(VENV) (a few minutes the first time; pip prints nothing meanwhile)"; \
	    $(BIN)/python -m pip install -q "$(TORCH)" || exit 1; \
	    echo '$(TORCH)' > $@; \
	fi

$(STAMP): setup.cfg pyproject.toml $(TORCH_STAMP)
	@echo "installing weathergen's dependencies and test tools into $(VENV) (a minute or two)"
	$(BIN)/python -m pip install -q ".[test]"
	touch $(STAMP)

# A regular (non-editable) install, so that a file missing from the distribution fails here.
install: $(STAMP)
	rm -rf build    # a stale build/ would put removed modules into the wheel
	$(BIN)/python -m pip install -q --no-deps --force-reinstall .

# Whole test files go to the workers (--dist loadfile): a file's module fixtures are built once.
# `make test` runs the quick tests, `make test-slow` the end-to-end runs (marker `slow`); CI
# (.ci/run) runs both, one after the other.
test: install
	$(BIN)/ruff check .
	@echo "running the quick tests in $(TEST_WORKERS) processes: about 4 minutes on a 2-core CPU (make test-slow runs the end-to-end ones)"
	$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow" $(PYTEST_ARGS)

test-slow: install
	@echo "running the end-to-end tests (marker slow) in $(TEST_WORKERS) processes: about 6 minutes on a 2-core CPU"
	$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile -m slow $(PYTEST_ARGS)

# The dependency floors of setup.cfg, installed exactly; torch as for `make test`.
test-oldest:
	test -x $(OLDEST)/bin/python || $(PYTHON) -m venv $(OLDEST)
	$(OLDEST)/bin/python -m pip install -q "$(TORCH)"
	$(OLDEST)/bin/python -m pip install -q -c constraints/oldest.txt ".[test]"
	$(OLDEST)/bin/python -m pip install -q --no-deps --force-reinstall .
	$(OLDEST)/bin/python -m pip check
	$(OLDEST)/bin/pytest -q $(PYTEST_ARGS)

# Into out/demo, so that the README's first command (`weathergen render`, into out/snow) is free.
demo: install
	@echo "rendering snow into the bundled demo scene (seconds)"
	$(BIN)/weathergen render --preset snow --out out/demo --overwrite
	$(BIN)/weathergen preview out/demo
	@echo "Next: activate the environment with '. $(VENV)/bin/activate' (or run $(BIN)/weathergen ...)"

bench: install
	$(BIN)/python speed/bench.py
	$(BIN)/python speed/bench_fog.py $(if $(FOG_BEFORE),--before $(FOG_BEFORE))
	$(BIN)/python speed/bench_core.py $(if $(CORE_BEFORE),--before $(CORE_BEFORE))
	$(BIN)/python speed/bench_field.py
	$(BIN)/python speed/bench_combined.py
	$(BIN)/python speed/bench_atmosphere.py
	$(BIN)/python speed/bench_models.py
	$(BIN)/python speed/bench_attack.py --checkpointing both
	$(BIN)/python speed/bench_training.py
	$(BIN)/python speed/bench_batch.py
	$(BIN)/python speed/bench_quick_look.py
	if $(BIN)/python -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then \
	  $(BIN)/python speed/bench_batch.py --device cuda --models raft --batch-sizes 1 4 8 --steps 5; fi

images: install
	$(BIN)/python scripts/make_images.py $(if $(REAL),--real $(REAL) --real-dataset $(REAL_DATASET)) \
	    $(if $(DEPTH_SCALE),--depth-scale $(DEPTH_SCALE))

cli-docs: install
	$(BIN)/python scripts/make_cli_docs.py

# The probe needs torch alone, so that a machine without CUDA is told at once, before any install.
gpu-check: $(TORCH_STAMP)
	@$(BIN)/python speed/gpu_check.py --probe
	$(MAKE) --no-print-directory install
	$(BIN)/python speed/gpu_check.py --json $(GPU_FIGURES)/gpu-check.json

clean:
	rm -rf $(VENV) $(OLDEST) build *.egg-info out
