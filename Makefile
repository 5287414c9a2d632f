# landbench: `make demo` runs the main job, `make test` the tests.
# Both bootstrap .venv (and Mesa's headless OpenGL through apt) on first use.
VENV := .venv
LB := $(VENV)/bin/landbench
PYTEST := $(VENV)/bin/python -m pytest
OUT ?= out/demo

.PHONY: all bootstrap demo test test-slow test-all snapshots perf clean

all: test

bootstrap:
	@./scripts/bootstrap.sh

## demo: fly the default scenario (vision camera on) and write its results, plus the terrain map
demo: bootstrap
	@mkdir -p "$(OUT)"
	$(LB) world --out "$(OUT)/world.png"
	$(LB) run --out "$(OUT)"
	@echo "demo: results in $(OUT)/ (summary.json, telemetry.parquet, scenario.toml, plots.png, camera.mp4, world.png)"

## test: the fast suite (CI runs this); the 15 slowest tests are listed so the time budget stays visible.
## Two processes (pytest-xdist), whole files per process so module fixtures are built once;
## TEST_JOBS=1 runs them in one process.
TEST_JOBS ?= 2
test: bootstrap
	$(PYTEST) -q -n $(TEST_JOBS) --dist loadfile --durations=15

## test-slow: the long checks (full descents, campaigns), marked @pytest.mark.slow
test-slow: bootstrap
	$(PYTEST) -q -n $(TEST_JOBS) --dist loadfile -m slow --durations=15

test-all: bootstrap
	$(PYTEST) -q -m "slow or not slow"

## snapshots: rewrite the replay metric snapshot (tests/snapshots/replay_segment.json) after an intended change;
## the tolerances (tests/snapshots/*.tolerances.json) are kept. Review the diff before committing it.
snapshots: bootstrap
	$(PYTEST) -q tests/test_record_replay.py -k snapshot --regen-snapshots

## perf: benchmark figures quoted in the README
perf: bootstrap
	$(LB) perf

clean:
	rm -rf $(VENV) out .pytest_cache *.egg-info
