"""Importers of formats that are defined by one of shiftkit's envs (the VPACE/LfGP buffers hold the
panda-play observation): they need the env registry, which the pipeline core may not import, so
they live here; `shiftkit import` finds them beside the core's (`pipelines/sources/`)."""
