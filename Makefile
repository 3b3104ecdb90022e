# Every target sets up .venv by itself when it is missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
OUT ?= out

.PHONY: run scan-demo test check bench image clean

$(BIN)/flyscan: pyproject.toml
	bash scripts/system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

run: $(BIN)/flyscan
	$(BIN)/python scripts/demo.py --data $(OUT)/service

scan-demo: $(BIN)/flyscan
	$(BIN)/flyscan scan --demo --out $(OUT)/demo

# Every test: on every core (a test module's tests stay on one worker: they share set-up), then
# those another worker's load would change (marked alone), one at a time on an idle machine.
test: $(BIN)/flyscan
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "not alone"; parallel=$$?; \
	$(BIN)/python -m pytest -q -m alone; serial=$$?; \
	test $$parallel -eq 0 -a $$serial -eq 0

# The loop of work: the core, the simulator, the clients, the API in-process and the layers.
check: $(BIN)/flyscan
	$(BIN)/python -m pytest -q -n auto --dist loadfile tests/scanner_core tests/simulator \
		tests/clients tests/service/test_api_inprocess.py tests/test_layers.py

# The reference parts' meshes are read where MESHES points (a folder with their manifest.json).
bench: export FLYSCAN_MESHES = $(MESHES)
bench: $(BIN)/flyscan
	@test -n "$(MESHES)" || { echo "make bench MESHES=DIR: the folder of the reference meshes" \
		"and their manifest.json"; exit 2; }
	bash scripts/system-deps.sh bench
	$(BIN)/pip install --quiet -e '.[test,bench]'
	$(BIN)/flyscan bench stripe --out $(OUT)/bench/stripe
	$(BIN)/flyscan bench scan --out $(OUT)/bench/scan
	$(BIN)/flyscan bench simulate --out $(OUT)/bench/simulate
	$(BIN)/flyscan bench service --out $(OUT)/bench/service
	$(BIN)/flyscan bench pose --out $(OUT)/bench/pose
	$(BIN)/flyscan bench coarse --out $(OUT)/bench/coarse
	$(BIN)/flyscan bench hardware --out $(OUT)/bench/hardware
	$(BIN)/flyscan bench surfaces --out $(OUT)/bench/surfaces
	$(BIN)/flyscan bench calibrate --out $(OUT)/bench/calibrate
	$(BIN)/flyscan bench edges --out $(OUT)/bench/edges

# docker/Dockerfile built with buildah on a debootstrapped base, run, and a scan through it; as
# root, installs buildah and debootstrap when missing (docs/docker.md). No .venv needed.
image:
	$(PYTHON) docker/build_local.py

clean:
	rm -rf $(VENV) $(OUT) *.egg-info
