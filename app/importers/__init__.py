"""Importers of formats that are defined by one of shiftkit's envs (the VPACE/LfGP buffers hold the
panda-play observation): they need the env registry, which the dataset layer may not import, so
they live here and register into `shiftkit.datasets.importers.IMPORTERS` beside the dataset layer's
own. Importing this package imports every module in it; the application loads it
(`shiftkit.app.plugins`)."""

from shiftkit.envs.registry import import_modules

import_modules(__name__, __path__)
