# Everything runs in a local virtual environment that the targets create on first use.
# torch==2.13.0 is installed first, on its own, so that nothing that depends on torch pulls a CUDA build.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-dev
OUT    ?= out

.PHONY: install demo train-cc test lint bench bench-install bench-speed bench-solver bench-formfactors \
	bench-accuracy bench-hierarchical bench-hierarchical-quick bench-images bench-variants bench-generator bench-kernel \
	bench-geometry-grad bench-cc clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/interreflect demo --out $(OUT)/demo

train-cc: $(STAMP)
	$(BIN)/interreflect train-cc --data $(OUT)/cc-data

lint: $(STAMP)
	$(BIN)/ruff check .

# The whole suite on 2 workers (1 torch thread each), then the numerical core again in one process with torch's
# default thread count (batched LU on torch 2.13 CPU breaks with 2 threads: the paths must not depend on 1 thread).
test: $(STAMP) lint
	$(BIN)/python -m pytest -q -n 2 --doctest-modules torch_interreflect tests
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/solver tests/formfactors tests/layers tests/camera tests/accuracy \
		tests/geometry/test_contacts.py tests/geometry/test_scene.py tests/geometry/test_derived.py tests/test_unique.py tests/test_lights.py \
		tests/test_lights_grad.py tests/test_sky_openings.py tests/geometry/test_openings.py tests/geometry/test_gaps.py \
		tests/training/test_generator.py tests/training/test_refine_lm.py

bench-formfactors: $(STAMP)
	$(BIN)/python -m benchmarks.formfactors --quick

bench-hierarchical: $(STAMP)
	$(BIN)/python -m benchmarks.hierarchical

bench-hierarchical-quick: $(STAMP)
	$(BIN)/python -m benchmarks.hierarchical --quick

bench-kernel: $(STAMP)
	$(BIN)/python -m benchmarks.kernel
	$(BIN)/python -m benchmarks.generate_throughput

bench-geometry-grad: $(STAMP)
	$(BIN)/python -m benchmarks.geometry_grad
	$(BIN)/python -m benchmarks.image_grad

bench-solver: $(STAMP)
	$(BIN)/python -m benchmarks.solver

bench-accuracy: $(STAMP)
	$(BIN)/python -m benchmarks.accuracy --quick

bench-images: bench-install
	DRJIT_LIBLLVM_PATH=$${DRJIT_LIBLLVM_PATH:-libLLVM.so.19.1} $(BIN)/python -m benchmarks.images --quick

bench-variants: bench-install
	DRJIT_LIBLLVM_PATH=$${DRJIT_LIBLLVM_PATH:-libLLVM.so.19.1} $(BIN)/python -m benchmarks.variants --quick

# the colour-constancy study: 3 training seeds, held-out and Mitsuba path-traced test sets (README states its time)
bench-cc: bench-install
	DRJIT_LIBLLVM_PATH=$${DRJIT_LIBLLVM_PATH:-libLLVM.so.19.1} $(BIN)/python -m benchmarks.colour_constancy --study

bench-generator: $(STAMP)
	$(BIN)/python -m benchmarks.generator

bench-install: $(STAMP)
	command -v apt-get >/dev/null && (apt-get update -qq && apt-get install -y -qq libllvm19) || true
	$(BIN)/python -m pip install -q -e '.[dev,bench]'

bench-speed: bench-install
	$(BIN)/python -m benchmarks.speed_vs_error --quick

bench: bench-formfactors bench-solver bench-speed bench-accuracy bench-hierarchical-quick

clean:
	rm -rf $(OUT) .pytest_cache .ruff_cache
