# `make run` and `make test` set up everything they need in .venv by themselves.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-dev
RUN_STAMP := $(VENV)/.installed-run
CONFIG ?= configs/kuka_lwr_sim.toml
ARGS ?= --duration 10
# the extras `make test` installs (.ci/run installs the same in its other Pythons' venvs)
EXTRAS := dev,sim,modbus,ethercat,can,record,plot,foxglove,zenoh,docs,bench
RUN_EXTRAS := sim,record

.PHONY: run lint test suite check docs figures bench bench-quick clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install -q -e '.[$(EXTRAS)]'
	touch $@

# `make run` needs only the simulator and the recorder; a venv `make test` set up has them
$(RUN_STAMP): $(PY) pyproject.toml
	@if [ -f $(STAMP) ] && [ $(STAMP) -nt pyproject.toml ]; then :; else $(PY) -m pip install -q -e '.[$(RUN_EXTRAS)]'; fi
	touch $@

run: $(RUN_STAMP)
	$(PY) -m aiohal $(CONFIG) $(ARGS)

# ruff checks every Python file; ruff format and mypy cover the three packages
lint: $(STAMP)
	$(VENV)/bin/ruff check aiohal drivers controllers tests benchmarks examples
	$(VENV)/bin/ruff format --check aiohal drivers controllers
	$(VENV)/bin/mypy aiohal drivers controllers

test: lint
	@$(MAKE) --no-print-directory suite

# The suite in an installed venv (.ci/run: `make suite PY=.venv312/bin/python`). The tests that
# need no real time run in parallel, one worker more than cores (pytest-xdist; a file's tests on
# one worker, so that its module fixtures start once): they wait on subprocesses and sleeping
# loops, so on 2 cores 3 workers took 348 s where 2 took 390 s and 4 took 352 s (the parallel
# part of `make suite WORKERS=n`).
# Then the realtime-marked ones, alone. Each part names its 20 slowest tests: one over 20 s
# says why in a comment.
WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))
suite:
	$(PY) -m pytest -n $(WORKERS) --dist loadfile -m "not realtime" --durations=20
	$(PY) -m pytest -m realtime --durations=20

check: $(STAMP)
	$(PY) -m aiohal check $(CONFIG)

bench: $(STAMP)
	mkdir -p bench-results
	$(PY) -m benchmarks.tick --json bench-results/tick.json
	$(PY) -m benchmarks.breakdown --json bench-results/breakdown.json
	$(PY) -m benchmarks.scaling --json bench-results/scaling.json
	$(PY) -m benchmarks.overhead --json bench-results/overhead.json
	$(PY) -m benchmarks.overhead --interleave 500 --clock realtime --json bench-results/overhead_realtime.json
	$(PY) -m benchmarks.idle_wait --json bench-results/idle_wait.json
	$(PY) -m benchmarks.robots --json bench-results/robots.json
	$(PY) -m benchmarks.gc_pauses --json bench-results/gc_pauses.json
	$(PY) -m benchmarks.isolated --json bench-results/isolated.json
	$(PY) -m benchmarks.kernel_call --json bench-results/kernel_call.json
	$(PY) -m benchmarks.pipe --json bench-results/pipe.json
	$(PY) -m benchmarks.shm_client --json bench-results/shm_client.json
	$(PY) -m benchmarks.zenoh_bridge --json bench-results/zenoh_bridge.json
	$(PY) -m benchmarks.canopen --json bench-results/canopen.json
	$(PY) -m benchmarks.host_gaps --json bench-results/host_gaps.json
	$(PY) -m benchmarks.udp --json bench-results/udp.json
	$(PY) -m benchmarks.fig7 --json bench-results/fig7.json
	$(PY) -m benchmarks.tick_phase $$([ "$$(id -u)" = 0 ] && echo --fifo) --json bench-results/tick_phase.json
	@if [ "$$(id -u)" = 0 ]; then $(PY) -m benchmarks.ethercat --json bench-results/ethercat.json; else echo "benchmarks.ethercat skipped: needs root"; fi
	@if [ "$$(id -u)" = 0 ]; then $(PY) -m benchmarks.whole_robot --json bench-results/whole_robot.json; else echo "benchmarks.whole_robot skipped: needs root"; fi

# a few of the benchmarks, shortened: a first look in a few minutes (bench takes about 30)
bench-quick: $(STAMP)
	mkdir -p bench-results/quick
	$(PY) -m benchmarks.tick --seconds 2 --json bench-results/quick/tick.json
	$(PY) -m benchmarks.breakdown --seconds 2 --warmup 0.5 --json bench-results/quick/breakdown.json
	$(PY) -m benchmarks.overhead --seconds 1 --warmup 0.5 --repeat 2 --json bench-results/quick/overhead.json
	$(PY) -m benchmarks.robots --seconds 2 --json bench-results/quick/robots.json
	$(PY) -m benchmarks.kernel_call --rounds 5 --json bench-results/quick/kernel_call.json

# the site (docs/ and the API reference from the docstrings) into site/; any warning fails it
docs: $(STAMP)
	$(PY) -c 'import mkdocs, mkdocstrings_handlers.python' 2>/dev/null || $(PY) -m pip install -q -e '.[docs]'
	$(VENV)/bin/mkdocs build --strict

figures: $(STAMP)
	$(PY) examples/plot_circles.py docs/img/circles.png

clean:
	rm -rf $(VENV) .venv3?? build site *.egg-info
