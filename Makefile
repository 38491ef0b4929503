# tvopt-codegen developer commands. Every target builds the virtual environment first,
# so `make demo` and `make test` work on a fresh machine with only Python 3.11+.

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CORE := $(VENV)/.core
INSTALLED := $(VENV)/.installed
READY := $(VENV)/.compiled
EXAMPLES := integrator unicycle_switch two_unicycles_barrier pvtol flexible_joint unicycle_ring arm_on_line planar_arm3

.PHONY: test-fast test-durations coverage-fast bench-tests bench-embedded tune-example
.PHONY: all demo figures bench bench-baseline bench-derive bench-representation bench-sweep bench-sweep-scale bench-commands sweep-example robust-example eso-example reference-noise fuzz test lint typecheck check regen check-generated update-golden clean

all: test

# pip compiles the bytecode of what it installs one file after another (20 of the 33 s
# the core takes); compileall does it on every core at once, in 2 s. The bytecode is
# needed: where PYTHONDONTWRITEBYTECODE is set, every command would otherwise compile
# sympy again. (A file written for another Python version fails to compile, as it does
# under pip: that is not an error here.)
SITE = $$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
COMPILE_SITE = $(PY) -m compileall -q -j 0 $(SITE) > /dev/null 2>&1 || true

# The core alone (sympy, numpy, scipy, jinja2, matplotlib): all the demo needs.
$(CORE): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --no-compile -e .
	$(COMPILE_SITE)
	touch $(CORE)

# Everything the tests touch: the dev tools and every optional integration.
$(INSTALLED): $(CORE)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile -e '.[dev,all]'
	$(COMPILE_SITE)
	touch $(INSTALLED)

# The package's bytecode, as installing a wheel leaves it: an editable install writes
# none itself, and where PYTHONDONTWRITEBYTECODE is set (this CI machine, most container
# images) every command compiled the package's 15,000 lines anew, 0.13-0.18 s of a small
# one. Python still checks each file against its source: an edit is never run stale.
$(READY): $(INSTALLED) $(shell find tvopt_codegen -name "*.py")
	$(PY) -m compileall -q tvopt_codegen
	touch $(READY)

## demo: generate the bundled unicycle example into build/demo, simulate it, check the theorem
## (installs the core alone; `make test` adds the rest)
demo: $(CORE)
	$(PY) -m compileall -q tvopt_codegen
	mkdir -p build
	$(PY) -m tvopt_codegen generate unicycle_switch --out build/demo
	$(PY) -m tvopt_codegen simulate unicycle_switch --out build/demo

## figures: regenerate the paper's Figs. 1-3 in docs/figures from the bundled examples
figures: $(READY)
	mkdir -p build/figures docs/figures
	for name in $(EXAMPLES); do \
	  $(PY) -m tvopt_codegen simulate $$name --out build/figures/$$name || exit 1; \
	  for stem in paths convergence constraints; do \
	    if [ -f build/figures/$$name/$${name}_$$stem.png ]; then \
	      cp build/figures/$$name/$${name}_$$stem.png docs/figures/; fi; \
	  done; \
	done

# pytest caches each test module as its assertion rewriter compiled it (in
# tests/__pycache__), unless PYTHONDONTWRITEBYTECODE is set, as it is on this CI machine:
# then every worker of every run rewrote and compiled the 85 test modules again, 4 s of
# each run's 9 s of collection. An empty value is unset to Python.
PYTEST := PYTHONDONTWRITEBYTECODE= $(PY) -m pytest

## test: the whole test suite
test: $(READY)
	$(PYTEST) -n auto --dist worksteal

## test-fast: the quick part of the suite (no test over 0.1 s in tests/durations.json), on
##   every core: what a contributor runs after each change
test-fast: $(READY)
	$(PYTEST) -n auto --dist worksteal -m "not slow"

## test-durations: the whole suite once more, writing each test's seconds to
##   tests/durations.json (which tests are slow)
test-durations: $(READY)
	TVOPT_TEST_DURATIONS=tests/durations.json $(PYTEST) -n auto --dist worksteal

## bench-tests: the whole suite on one core and on every core, and make test-fast, timed;
##   BASELINE=REV: make test of REV (a worktree with its own venv) and of this tree, alternated;
##   TREE=REV measures a clean worktree of REV in place of the checkout; ROUNDS=N;
##   COLD=1 also runs both with nothing kept from earlier runs (compiled libraries, .test-cache)
bench-tests: $(READY)
	$(PY) benchmarks/bench_tests.py $(if $(BASELINE),--baseline $(BASELINE)) \
	  $(if $(TREE),--tree $(TREE)) $(if $(ROUNDS),--rounds $(ROUNDS)) $(if $(COLD),--cold) \
	  --write benchmarks/TESTS.md

## coverage-fast: which lines of the package make test-fast runs; fails if a module is left
##   unexercised (tests/coverage_check.py)
coverage-fast: $(READY)
	PYTHONDONTWRITEBYTECODE= $(PY) -m coverage run --source=tvopt_codegen -m pytest -q -p no:xdist -m "not slow"
	$(PY) -m coverage report --sort=cover
	$(PY) -m tests.coverage_check

## bench: C and NumPy controllers against CasADi (installs the bench extra: casadi, cffi)
bench: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_c.py --write benchmarks/RESULTS.md

## bench-embedded: instructions per call (QEMU -icount), memory and stack of every example's C
##   on a Cortex-M4F, double against single and against CasADi (benchmarks/EMBEDDED.md; needs
##   .ci/run's ARM toolchain and QEMU)
bench-embedded: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_embedded.py --write benchmarks/EMBEDDED.md

## bench-derive: cold generate per N = 1..256 of unicycle_ring: wall, stage shares, memory, ops, vs CasADi;
##   ENGINE=symengine|sympy, SIZES=32,128,1024, ROUNDS=1 narrow it
bench-derive: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_derive.py $(if $(ENGINE),--engine $(ENGINE)) $(if $(SIZES),--sizes $(SIZES)) \
	  $(if $(ROUNDS),--rounds $(ROUNDS)) --write benchmarks/DERIVE.md

## bench-sweep: sweep throughput on unicycle_switch vs simulate per sample and CasADi's cvodes map
bench-sweep: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_sweep.py --write benchmarks/SWEEP.md

## bench-commands: cold generate, simulate and report of every bundled example (benchmarks/COMMANDS.md);
##   BASELINE=REV measures that commit beside the checkout, run for run; ENGINES=symengine,sympy
##   runs the checkout on each engine in turn
bench-commands: $(READY)
	$(PY) benchmarks/bench_commands.py $(if $(BASELINE),--baseline $(BASELINE)) \
	  $(if $(ENGINES),--engines $(ENGINES)) --write benchmarks/COMMANDS.md

## bench-baseline: cold generate of rings of 32 and 128 agents and chain12, BASELINE=REV beside the checkout
bench-baseline: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_baseline.py --baseline $(BASELINE) --write benchmarks/BASELINE.md

## bench-representation: the gradient jet on sympy and on SymEngine (benchmarks/REPRESENTATION.md)
bench-representation: $(READY)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/bench_representation.py --write benchmarks/REPRESENTATION.md

## bench-sweep-scale: a sweep's client memory at 10^4..10^6 samples, first progress, throughput
bench-sweep-scale: $(READY)
	$(PY) benchmarks/sweep_scale.py --write benchmarks/SWEEP.md

## sweep-example: the user guide's 1,000-sample PVTOL sweep with mass and inertia mismatch
sweep-example: $(READY)
	rm -rf build/sweep-pvtol
	mkdir -p build docs/figures
	$(PY) -m tvopt_codegen sweep pvtol --samples 1000 --seed 2026 \
	  --plant-param m='normal(1, 0.1)' --plant-param J='normal(1, 0.1)' --out build/sweep-pvtol
	cp build/sweep-pvtol/sweep_histograms.png docs/figures/sweep_pvtol_histograms.png
	cp build/sweep-pvtol/sweep_worst.png docs/figures/sweep_pvtol_worst.png
	cp build/sweep-pvtol/summary.md docs/sweep-pvtol.md

## tune-example: tune PVTOL and planar_arm3 against sweeps of the mismatched plant, CMA-ES against
##   random search of the same budget, determinism and a SIGTERM-resume checked (benchmarks/TUNE.md,
##   the worked example of docs/tune.md; about 10 minutes on 2 cores)
tune-example: $(READY)
	mkdir -p docs/figures
	$(PY) benchmarks/bench_tune.py --write benchmarks/TUNE.md --doc docs/tune.md

## robust-example: integral action, the observer and limits judged by 1,000-sample sweeps (docs/robust.md)
robust-example: $(READY)
	mkdir -p docs/figures
	$(PY) benchmarks/robust_example.py --write docs/robust.md

## eso-example: the extended-state observer against the other options, 200-sample sweeps at 1 kHz
##   on three plants (docs/eso.md)
eso-example: $(READY)
	$(PY) benchmarks/eso_example.py --write docs/eso.md

## reference-noise: tracking from sampled references at three noise levels (docs/references-noise.md)
reference-noise: $(READY)
	$(PY) benchmarks/reference_noise.py --write docs/references-noise.md

## features-doc: regenerate docs/features.md from the feature matrix (tvopt_codegen/spec/features.py)
.PHONY: features-doc
features-doc: $(READY)
	$(PY) -m tvopt_codegen.spec.features > docs/features.md

## fuzz: the differential fuzzer (docs/fuzz.md): CASES random cases (default 200) drawn from SEED
##   (default: a fresh one, printed); CASE=kind:size:features:seed replays one case; C_RATE and
##   FMU_RATE are the shares of cases also run in C and in the FMU; LOG=file keeps one line a case;
##   WORKERS processes run the cases (default 1; the cases and their ends are the same)
CASES ?= 200
C_RATE ?= 0.05
FMU_RATE ?= 0.02
WORKERS ?= 1
fuzz: $(READY)
	$(PY) -m tests.fuzzing --cases $(CASES) --c-rate $(C_RATE) --fmu-rate $(FMU_RATE) --workers $(WORKERS) \
	  $(if $(SEED),--seed $(SEED)) $(if $(CASE),--case $(CASE)) $(if $(LOG),--log $(LOG))

## lint: ruff and mypy (strict) over the package
lint: $(READY)
	$(PY) -m ruff check tvopt_codegen tests benchmarks
	$(PY) -m mypy

## regen: regenerate the committed controllers in generated/ from the bundled examples
regen: $(READY)
	mkdir -p generated/c
	for name in $(EXAMPLES); do \
	  $(PY) -m tvopt_codegen generate $$name --out generated --quiet || exit 1; \
	  $(PY) -m tvopt_codegen generate $$name --backend c --out generated/c --quiet || exit 1; \
	done

## check-generated: fail if generated/ is not what the current code generates
check-generated: regen
	git diff --exit-code generated/

## update-golden: rewrite tests/golden from the current output (review the diff!)
update-golden: $(READY)
	$(PY) -m pytest tests/test_report.py -k golden --update-golden

check: lint test

clean:
	rm -rf build .pytest_cache .mypy_cache .ruff_cache .test-cache
