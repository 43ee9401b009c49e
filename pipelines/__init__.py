"""shiftkit.pipelines: stage protocol and registry, pipeline configs, runner, executors, LeRobot IO,
raw-episode format, importers, hub and CLI."""
