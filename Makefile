# One place for the commands the README promises. Every target works on a fresh machine of this kind.
PY     ?= .venv/bin/python
PIP    ?= .venv/bin/pip
STAMP  := .venv/.installed

.PHONY: setup demo test bench results clean

$(STAMP): pyproject.toml
	@if ! ldconfig -p | grep -q libusb-1.0; then \
	  (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 libgomp1) || \
	  { echo "error: open3d needs the Debian package libusb-1.0-0; install it as root" >&2; exit 1; }; fi
	test -x $(PY) || python3 -m venv .venv
	$(PIP) install -q --disable-pip-version-check torch==2.13.0
	$(PIP) install -q --disable-pip-version-check -e ".[dev]"
	.venv/bin/rerun analytics disable >/dev/null  # the viewer must not phone home
	touch $(STAMP)

setup: $(STAMP)

# The main job: a short closed-loop clearance evaluation of Diffusion-Suction that writes a replay.
demo: $(STAMP)
	$(PY) eval/clearance.py --policy diffusion --objects mixed --layout scattered --episodes 1 --parcels 6 \
	  --seed 0 --record runs/demo/replays --out runs/demo/clearance.json

# Lint (ruff, pyproject's [tool.ruff]) and type-check the env's public API (mypy, [tool.mypy]) before the tests.
test: $(STAMP)
	.venv/bin/ruff check .
	$(PY) -m mypy
	$(PY) -m pytest -n 2 -q

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

# Every published number: test data, AP, clearance, ablations, benchmarks -> results/ and benchmarks/RESULTS.md.
# Resumable (finished parts are kept in runs/results); trains nothing unless RESULTS_ARGS has --train.
# On Ray: make results RESULTS_ARGS="--backend ray --workers 32 --ray-address auto"
RESULTS_ARGS ?=
results: $(STAMP)
	$(PY) -m eval.results $(RESULTS_ARGS)

clean:
	rm -rf .venv build *.egg-info .pytest_cache
