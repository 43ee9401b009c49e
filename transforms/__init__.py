"""shiftkit.transforms: the offline stages. Importing this package imports every module in it, and
each stage module registers its stages (`@register_stage`), so a new stage is one new module. The
application loads it (`shiftkit.app.plugins`)."""

from shiftkit.envs.registry import import_modules

import_modules(__name__, __path__)
