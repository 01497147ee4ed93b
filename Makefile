# Two entry points for a fresh machine: `make run` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test setup bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(BIN)/mtcw run

# The real-Prometheus integration test needs Debian's prometheus; install it where we may (root + apt).
PROM_STAMP := $(VENV)/.prometheus
$(PROM_STAMP): | $(STAMP)
	@command -v prometheus >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends prometheus >/dev/null 2>&1 || \
	    { apt-get update -q >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends prometheus >/dev/null 2>&1; }; } || \
	  echo "note: Debian package prometheus not installed; its test will be skipped"; }
	@touch $@

# The browser test drives Debian's chromium (Playwright, from the test extras, uses the system browser:
# no browser download); install it where we may (root + apt), else its test is skipped.
CHROMIUM_STAMP := $(VENV)/.chromium
$(CHROMIUM_STAMP): | $(STAMP)
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1 || \
	    { apt-get update -q >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1; }; } || \
	  echo "note: Debian package chromium not installed; the browser test (tests/test_browser.py) will be skipped"; }
	@touch $@

test: $(STAMP) $(PROM_STAMP) $(CHROMIUM_STAMP)
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/mtcw bench --quick

clean:
	rm -rf $(VENV) out
