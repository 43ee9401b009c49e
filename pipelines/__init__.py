"""shiftkit.pipelines: the engine. The stage protocol, kinds and registry, pipeline configs, the
planner, the runner, work units, executors and the writer step; it reads its sources and writes its
datasets through the dataset layer (`shiftkit.datasets`) and names no stage, trainer or env family."""
