"""shiftkit.transforms: the offline stages. Importing this package registers every built-in stage."""

from shiftkit.transforms import cast, drop, filter_episodes, rename, resample, subsample, success_examples, trim  # noqa: F401
