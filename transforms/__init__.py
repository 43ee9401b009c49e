"""shiftkit.transforms: the offline stages. Importing this package registers every built-in stage."""

from shiftkit.transforms import (  # noqa: F401
    cast,
    depth_image,
    dimensions,
    drop,
    filter_episodes,
    force_matching,
    map_tasks,
    mode_labels,
    multiview,
    rename,
    replay_join,
    resample,
    resize,
    subsample,
    success_examples,
    trim,
)
