# Mechanics behind the README's two commands. Everything runs from a local virtualenv (.venv).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
export NUMBA_CACHE_DIR ?= $(CURDIR)/.numba_cache

.PHONY: setup warm demo test bench clean

# setup.py and the C sources: `pip install -e .` (re)builds the compositor's library in place.
$(VENV)/.installed: pyproject.toml setup.py $(wildcard canonical_core/rendering/*.c)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch first, pinned: the local CPU wheel (an unpinned torch downloads CUDA builds)
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[server,client,dev]'
	touch $@

setup: $(VENV)/.installed

# The service's start-up kernels compiled into numba's cache once (about two minutes on a fresh
# machine, more on a busy one), so that the services started next (the demo's, the tests') load them
# instead of compiling them within their start-up deadline. A few seconds once the cache is full.
warm: setup
	$(PY) -c "from server.warmup import warm_up; warm_up()"

# Main job: start the service on an embedded default and stream a sample capture into it.
demo: warm
	$(PY) -m client.cli demo --out out/demo

# The test command also installs what the tests need beyond the service: the [cluster] extra (Ray
# Serve, for tests/cluster), Debian's chromium, which the viewer's browser tests drive through
# Playwright (CI runs as root; `playwright install` is not used: it downloads from outside the registries),
# and curl, which the README's curl example (run by tests/test_readme.py) calls. Two workers
# (pytest-xdist), each taking whole test files, so that a file's fixtures (a service, a browser, the
# Ray cluster) are set up once, and in one process.
test: warm
	$(PY) -m pip install -q -e '.[cluster]'
	@test -x /usr/bin/chromium -a -x /usr/bin/curl || apt-get install -y chromium curl || (apt-get update && apt-get install -y chromium curl)
	@$(PY) -c "import playwright" 2>/dev/null || $(PY) -m pip install -q playwright
	$(PY) -m pytest -q -n 2 --dist loadfile tests

bench: setup
	$(PY) -m pip install -q -e '.[bench]'
	$(PY) bench/fold.py

clean:
	rm -rf $(VENV) .numba_cache out
