# Two commands on a fresh machine with only python3 and make:
#   make demo   set-up, then the main job on the embedded default scene
#   make test   set-up, then the whole test suite (the documentation site included)
#   make docs   the documentation site into build/docs
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# rayoptics reads the lens files of its sample designs (lensfit bench-lenses --designs rayoptics and its
# tests); installed without its declared dependencies, which bring its Qt GUI (PySide6, hundreds of MB) that
# its file readers never import: these are the ones they do
RAYOPTICS := rayoptics==0.9.8 opticalglass==1.1.1 anytree==2.13.0 parsimonious==0.11.0 regex==2026.12.2 \
             transforms3d==0.4.2 json_tricks==3.17.3 deprecation==2.1.0 traitlets==5.16.1 xlrd==2.0.2 \
             openpyxl==3.1.5 et_xmlfile==2.0.0

.PHONY: setup demo test docs docs-figures readme-table clean

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "lensfit needs Python >= 3.11; found " + sys.version.split()[0] + ". Set PYTHON=/path/to/python3.11 and retry.")'
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || { echo "could not create a virtual environment with '$(PYTHON) -m venv'; on Debian/Ubuntu install python3-venv"; exit 1; }
	@echo "installing lensfit and its dependencies into $(VENV) (log: $(VENV)/pip.log) ..."
	@$(PY) -m pip install --quiet --upgrade pip > $(VENV)/pip.log 2>&1 || { cat $(VENV)/pip.log; exit 1; }
	@$(PY) -m pip install --quiet -e '.[test,docs]' >> $(VENV)/pip.log 2>&1 || { cat $(VENV)/pip.log; exit 1; }
	@$(PY) -m pip install --quiet --no-deps $(RAYOPTICS) >> $(VENV)/pip.log 2>&1 || { cat $(VENV)/pip.log; exit 1; }
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/lensfit dof --focal-length 25 --f-number 11 --focus-distance 1000 --sensor demo-7.2x4.8
	$(VENV)/bin/synth render data_specs/scenes/demo.toml --out out/demo --force
	$(VENV)/bin/lensfit fit out/demo --out out/demo_results.json --plot out/demo_fit.png --samples out/demo_samples.csv --force

# two worker processes (fewer on a one-core machine), each test file in one of them
test: setup
	$(PY) -m pytest -q -n auto --maxprocesses 2 --dist loadfile

# the documentation site into build/docs (strict: a warning fails); tests/docs/test_docs.py builds it too
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --config-file docs/mkdocs.yml --site-dir ../build/docs

# every example run again into out/examples/NAME/, its figure copied into its page
docs-figures: setup
	@for f in docs/examples/*.py; do n=$$(basename $$f .py); echo "$$f"; \
	  $(PY) $$f out/examples/$$n > /dev/null && cp out/examples/$$n/$$n.png docs/src/examples/img/ || exit 1; done

# the README's accuracy table again from the latest benchmark records (docs/validation/records/)
readme-table: setup
	$(PY) -m lensfit.bench.records --readme README.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
