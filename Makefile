# Fringescope — two commands: `make run` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
export NUMBA_THREADING_LAYER ?= workqueue
export NUMBA_CACHE_DIR ?= $(CURDIR)/.venv/numba-cache

.PHONY: run test test-parallel lint bench clean system-deps

# Re-install only when pyproject.toml changes (stamp files keep both targets idempotent).
$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.installed-run: pyproject.toml | $(BIN)/python
	@echo "[start] installing Fringescope and its dependencies into $(VENV) (first time only, about 1 min)"
	$(BIN)/pip install --progress-bar on -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

# The progress lines ([start] …) come from scripts/start_progress.py beside the server: the
# expected time to the first depth, then each start-up phase. Kernels are cached in NUMBA_CACHE_DIR.
run: $(VENV)/.installed-run
	@$(BIN)/python scripts/start_progress.py & exec $(BIN)/fringescope serve

# Debian packages the test suite drives for real: Chromium (browser tests) and podman (image build).
system-deps:
	@bash scripts/install-system-deps.sh

# The whole suite in one pytest process. `make test-parallel` runs it on $(TEST_WORKERS)
# pytest-xdist workers (`serial` tests, which assert wall-clock times or rates, alone after);
# on a 2-core machine it saves little, needs more memory in sum and has shown load-dependent
# failures (figures in the README's Development section), so it is not the default.
TEST_WORKERS ?= 2
# The fused reconstruction kernel compiles ~45 s per frame dtype and a fresh checkout has no
# kernel cache: uint8 compiles beside the type check, uint16 after it (staggered, so the two never
# rewrite numba's cache index at once), and the suite starts with both cached.
test: $(VENV)/.installed-dev system-deps
	$(BIN)/ruff check app tests benchmarks scripts
	@$(BIN)/python scripts/warm_kernels.py uint8 & warm=$$!; rc=0; \
	$(BIN)/mypy || rc=$$?; \
	$(BIN)/python scripts/warm_kernels.py uint16 || rc=$$?; \
	wait $$warm || rc=$$?; exit $$rc
	$(BIN)/python -m pytest -q --durations=40

test-parallel: $(VENV)/.installed-dev system-deps
	@shared=$$(mktemp -d) && trap 'rm -rf "$$shared"' EXIT && export FRINGESCOPE_TEST_SHARED_DIR=$$shared \
	&& rc=0 \
	&& { $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not serial" || rc=$$?; } \
	&& { $(BIN)/python -m pytest -q -m serial || rc=$$?; } \
	&& exit $$rc

bench: $(VENV)/.installed-dev
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
