# Set-up and entry points. Both targets create .venv when it is missing and reinstall when
# pyproject.toml changes (the stamp file is keyed on its hash).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell sha256sum pyproject.toml | cut -c1-16)

.PHONY: demo test bench cpu cpu-recipe cpu-claims cpu-transfer clean

$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	@echo "installing the project into $(VENV) (log: $(VENV)/pip.log)"
	@$(PY) -m pip install -e '.[test]' > $(VENV)/pip.log 2>&1 || { tail -40 $(VENV)/pip.log; exit 1; }
	@rm -f $(VENV)/.installed-*
	@touch $@

demo: $(STAMP)
	@bash scripts/demo.sh

cpu: $(STAMP)
	@bash scripts/cpu.sh

cpu-recipe: $(STAMP)
	@bash scripts/cpu_recipe.sh

cpu-claims: $(STAMP)
	@bash scripts/cpu_claims.sh

cpu-transfer: $(STAMP)
	@bash scripts/cpu_transfer.sh

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/policy_step.py

clean:
	rm -rf $(VENV) .pytest_cache
