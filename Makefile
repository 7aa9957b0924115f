# Quick start: `make run` (dry-run / main job) and `make test`. Both create .venv.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# + the aravis extra and the Debian packages the tests need (make test installs them)
ARAVIS_STAMP := $(VENV)/.aravis-installed
OUT    ?= out
# test workers (pytest-xdist), one test file at a time each: the real-time tests mostly wait on the clock, so two
# workers on a 2-core machine take ~0.6x the serial time; TEST_WORKERS=0 runs serially in this process
TEST_WORKERS ?= 2

.PHONY: setup run test bench clean aravis-deps

$(STAMP): pyproject.toml constraints.txt
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or: make PYTHON=/path/to/python3.11)"; exit 2; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test]'
	@touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/supervisor dry-run -o $(OUT)/dry-run

test: $(ARAVIS_STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# Aravis camera driver (the `aravis` extra): Debian's build deps for PyGObject and the GigE fake camera
# (aravis-tools), then the pip wheels. Needs root for apt-get; idempotent (dpkg check, stamp file).
APT_ARAVIS := libgirepository1.0-dev libcairo2-dev pkg-config gcc aravis-tools
# systemd: systemd-analyze checks the shipped unit
APT_TEST := $(APT_ARAVIS) systemd
$(ARAVIS_STAMP): $(STAMP) pyproject.toml constraints.txt
	@dpkg -s $(APT_TEST) >/dev/null 2>&1 || { apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(APT_TEST) >/dev/null; }
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test,aravis]'
	@touch $(ARAVIS_STAMP)

aravis-deps: $(ARAVIS_STAMP)

bench: $(STAMP)
	$(PY) benchmarks/bench_render.py
	$(PY) benchmarks/bench_localization.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
