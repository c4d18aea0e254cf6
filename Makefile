# The verbs people type. Every target that runs code depends on .venv, so each
# one works on a fresh machine by itself.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# the main job's case (make run, make vcan-run)
SIM_ARGS := --route full_road_section --mode auto --seed 1

.PHONY: setup run test test-fast lint jit bench tables tables-check clean \
        vcan-setup vcan-run vcan-shell vcan-test pil-setup pil

setup: $(STAMP)

# Re-install only when the dependency list changes (idempotent, fast when done).
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

run: $(STAMP)
	$(PY) -m hil run $(SIM_ARGS) --pace lockstep --out out/run

# the whole suite: the layer contracts, then every test (HIL, golden traces and slow ones too);
# the 15 slowest are listed at the end (where CI time goes)
test: lint jit
	$(PY) -m pytest -q -n 2 --dist loadgroup --durations=15

# numba's cache filled before the processes that load it start (tools/jit.py): the compiled
# tick takes about a minute to compile cold, tens of milliseconds to load
jit: $(STAMP)
	$(PY) -m tools.jit

# the unit tier: no HIL, no golden traces, no long simulation (a minute or so on a warm machine)
test-fast: lint
	$(PY) -m pytest -q -n 2 -m "not hil and not slow and not golden"

# the import layers firmware <- calib <- hil <- tools (import-linter contracts in pyproject.toml)
lint: $(STAMP)
	$(VENV)/bin/lint-imports --no-cache

# benchmarks: out/bench.json and a table (run on an idle machine)
bench: $(STAMP)
	$(PY) -m tools.bench --out out/bench.json

# the shipped calibrations as data (calib/data/*.json, designed afresh), then the C-portable
# coefficient tables and the A2L (c/generated) from them; -check fails when either is stale
tables: $(STAMP)
	$(PY) -m tools.calibration
	$(PY) -m tools.tables --out c/generated

tables-check: $(STAMP)
	$(PY) -m tools.calibration --check
	$(PY) -m tools.tables --out c/generated --check

# Real SocketCAN in User-mode Linux (hil/transport/vcan.py; docs/vcan.md): the bench on vcan0 in a real
# kernel where the host's has no CAN. vcan-setup installs the Debian packages (as root).
VCAN_PKGS := user-mode-linux can-utils iproute2

vcan-setup:
	@if command -v linux.uml >/dev/null && command -v candump >/dev/null && command -v ip >/dev/null; then \
	  echo "vcan-setup: User-mode Linux and can-utils are installed"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get install -y --no-install-recommends $(VCAN_PKGS) >/dev/null || \
	  { apt-get update -qq && apt-get install -y --no-install-recommends $(VCAN_PKGS); }; \
	else \
	  echo "vcan-setup: as root, type: apt-get install -y $(VCAN_PKGS)"; exit 2; \
	fi

# the make-run drive on socketcan vcan0 in UML, candump -L vcan0 recording beside it; then
# candump's frames against bus.log's, and the trace against hil sim's of the same case
vcan-run: $(STAMP) vcan-setup
	rm -rf out/vcan
	$(PY) -m hil vcan --timeout 1800 --candump out/vcan/candump.log -- \
	  $(PY) -m hil run $(SIM_ARGS) --pace lockstep -i socketcan -c vcan0 --out out/vcan
	$(PY) -m hil logdiff out/vcan/candump.log out/vcan/bus.log
	$(PY) -m hil sim $(SIM_ARGS) --key-file out/vcan/secoc.key --out out/vcan/sim --json >/dev/null
	@$(PY) -c 'import json, sys; a, b = (json.load(open(f))["trace_sha256"] for f in sys.argv[1:]); \
	  print(f"trace {a[:16]} on vcan0, {b[:16]} in hil sim:", "the same" if a == b else "DIFFERENT"); \
	  sys.exit(a != b)' out/vcan/report.json out/vcan/sim/report.json

# a shell in UML with vcan0 up: hil run and candump vcan0 side by side, as on any host with vcan
vcan-shell: $(STAMP) vcan-setup
	$(PY) -m hil vcan

# the tests that make sense on vcan0 (marker vcan), in UML
vcan-test: $(STAMP) vcan-setup jit
	$(PY) -m hil vcan --timeout 3000 -- $(PY) -m pytest -q -p no:cacheprovider -m vcan --durations=0

clean:
	rm -rf $(VENV) out .pytest_cache

# Processor in the loop (tools/pil.py; docs/pil.md): the C core cross-compiled for a Cortex-M4F
# and a Cortex-M7, run under QEMU on the recorded traces: bit-exact, its instructions per tick,
# flash, RAM and stack against the M4F budget and tests/golden/pil.json. pil-setup installs
# the Debian packages (as root).
PIL_PKGS := gcc-arm-none-eabi picolibc-arm-none-eabi qemu-system-arm

pil-setup:
	@if command -v arm-none-eabi-gcc >/dev/null && command -v qemu-system-arm >/dev/null && \
	  [ -f /usr/lib/picolibc/arm-none-eabi/picolibc.specs ]; then \
	  echo "pil-setup: the ARM toolchain, picolibc and QEMU are installed"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get install -y --no-install-recommends $(PIL_PKGS) >/dev/null || \
	  { apt-get update -qq && apt-get install -y --no-install-recommends $(PIL_PKGS); }; \
	else \
	  echo "pil-setup: as root, type: apt-get install -y $(PIL_PKGS)"; exit 2; \
	fi

pil: $(STAMP) pil-setup
	$(PY) -m tools.pil
