# The two commands of the README: `make demo` and `make test`.
# Each creates or refreshes the virtual environment itself, installs system
# packages when running as root (or prints the command to run), then runs.

PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
SYSPKG := libusb-1.0-0 libgomp1
TESTPKG := chromium

.PHONY: demo test test-all bench setup system-packages test-packages clean

demo: setup
	$(PY) -m phirie_jax.cli demo --out out/demo

# One XLA compilation cache for a test run, shared by the pytest workers and every process a test
# starts (conversions on the command line, Ray workers): a program compiled in one is read by the
# others. Made empty for each run and removed after it.
TESTCACHE = cache=$$(mktemp -d) && JAX_COMPILATION_CACHE_DIR=$$cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0.5

test: setup test-packages
	$(TESTCACHE) $(PY) -m pytest -n auto --dist loadfile -q; status=$$?; rm -rf $$cache; exit $$status

test-all: setup test-packages
	$(TESTCACHE) $(PY) -m pytest -n auto --dist loadfile -q -m ''; status=$$?; rm -rf $$cache; exit $$status

setup: system-packages $(STAMP)

# open3d needs libusb at import time. As root (CI) install it; otherwise say how.
system-packages:
	@missing=""; for p in $(SYSPKG); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else \
	    echo "missing system packages:$$missing"; \
	    echo "run: sudo apt-get update && sudo apt-get install -y$$missing"; exit 1; \
	  fi; \
	fi

# The viewer's browser test drives Debian's Chromium (headless). As root (CI) install it;
# otherwise say how (that test is skipped without it).
test-packages:
	@missing=""; for p in $(TESTPKG); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing test packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else \
	    echo "missing test packages:$$missing (the browser test is skipped)"; \
	    echo "run: sudo apt-get update && sudo apt-get install -y$$missing"; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "needs $(PYTHON) (Python >= 3.11) on PATH"; exit 1; }
	[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# the editable build's notice about same-named folders is for other layouts: silenced
	PYTHONWARNINGS=ignore $(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) out .pytest_cache
