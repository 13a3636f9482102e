# Aerograv — two commands: `make serve` and `make test` (README).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DATA   ?= $(CURDIR)/data
SAMPLE := sample_surveys/omolon-mini
# the suite's worker processes (pytest-xdist); each takes whole test files, so module fixtures are built once
TEST_WORKERS ?= 2

.PHONY: install browser test test-fast demo serve bench sample clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# Debian's Chromium for the browser tests (Playwright drives it; no browser download).
browser:
	@if [ ! -x /usr/bin/chromium ]; then \
	  if command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	      || echo "warning: could not install chromium; browser tests will be skipped"; \
	  else echo "warning: no apt-get; browser tests will be skipped"; fi; \
	fi

test: install browser
	$(VENV)/bin/ruff check app tests benchmarks
	$(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile

test-fast: install
	$(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile -m "not slow and not browser"

demo: install
	$(VENV)/bin/aerograv process $(SAMPLE) --out out/omolon-mini
	@echo "outputs written to $(CURDIR)/out/omolon-mini"

# byte-compiled once: every web job is a new process importing the app, and with
# PYTHONDONTWRITEBYTECODE set nothing else would write the .pyc files (~0.3 s per job)
serve: install
	$(PY) -m compileall -q app >/dev/null
	AEROGRAV_DATA_DIR=$(DATA) $(VENV)/bin/aerograv serve --host 127.0.0.1 --port 8000 --bootstrap $(SAMPLE)

bench: install
	$(PY) benchmarks/run_all.py

# Regenerate the committed sample survey.
sample: install
	rm -rf $(SAMPLE)
	$(VENV)/bin/aerograv simulate --preset omolon-mini --out $(SAMPLE) --seed 1

clean:
	rm -rf $(VENV) out .pytest_cache
