"""What the shiftkit application plugs into the registries of the layers below it: its stages
(`shiftkit.transforms`, into the engine's `STAGES`) and its importers of env-defined formats
(`shiftkit.app.importers`, into the dataset layer's `IMPORTERS`).

This module is the `shiftkit.plugins` entry point (pyproject.toml): a registry imports it on its
first lookup, in every process that asks (a pipeline's workers under any executor too), so neither
the engine nor the dataset layer names a package above it. Another installed package adds its own
stages or importers the same way, with an entry point of its own in that group.
"""

import shiftkit.app.importers  # noqa: F401 - registers the importers of env-defined formats
import shiftkit.transforms  # noqa: F401 - registers the stages
