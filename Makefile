# The two set-up commands (see README): `make demo` and `make test`. Both create the environment
# when it is missing. `make lint` checks style and the dependency direction (CI runs it too).
SHELL := /bin/bash
export MUJOCO_GL ?= egl
export HF_HUB_OFFLINE ?= 1
export TOKENIZERS_PARALLELISM ?= false

.PHONY: demo test lint format
demo:
	@v=$$(scripts/ensure-env.sh) && "$$v/bin/shiftkit" demo --out outputs/demo --overwrite

test:
	@v=$$(scripts/ensure-env.sh) && "$$v/bin/python" -m pytest -q $(PYTEST_ARGS)

lint:
	@v=$$(scripts/ensure-env.sh) && "$$v/bin/ruff" check . && "$$v/bin/ruff" format --check . && scripts/lint-imports.sh "$$v"

format:
	@v=$$(scripts/ensure-env.sh) && "$$v/bin/ruff" check --fix . && "$$v/bin/ruff" format .
