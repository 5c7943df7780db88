# calib: two commands on a fresh clone: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: install demo demo-all test validate lint bench clean screenshots

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	PATH=$(CURDIR)/$(BIN):$$PATH bash sample_data/demo.sh

# every method (Ferraris, align, RIMU, turntable 3 and 9 cycles, static) on its
# example plan in sample_data/plans/: simulate, fit, report (a few minutes)
demo-all: $(STAMP)
	PATH=$(CURDIR)/$(BIN):$$PATH bash sample_data/demo_all.sh

test: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -n 2 --dist loadfile

# the HTML report of every method, --with effect and diagnosis rendered by headless
# Chromium -> docs/figures/report-*.png (calib_cli/validation/report_cases.py);
# installs the distribution's chromium package where it is missing (needs root or sudo)
screenshots: $(STAMP)
	command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	  { $$(command -v sudo) apt-get update && $$(command -v sudo) apt-get install -y --no-install-recommends chromium; }
	PATH=$(CURDIR)/$(BIN):$$PATH MPLBACKEND=Agg bash sample_data/screenshots.sh

# make validate K=turntable: one named part alone (tests marked part("turntable")), or
# K=EXPR: the slow tests whose names match EXPR (pytest -k)
validate: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m slow tests $(if $(K),--part "$(K)")

lint: $(STAMP)
	$(BIN)/ruff check calib_cli tests

# each benchmark prints its figures against a baseline measured in the same run
BENCHES := benchmarks.bench benchmarks.bench_acquire benchmarks.bench_batch benchmarks.bench_turntable benchmarks.bench_import benchmarks.bench_plan benchmarks.bench_cli benchmarks.bench_fclogs

bench: $(STAMP)
	for b in $(BENCHES); do echo "== $$b"; MPLBACKEND=Agg $(BIN)/python -m $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo_out
