"""Render Markdown cards from provenance dicts with the templates in `templates/`."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from string import Template
from typing import Any

THESIS = (
    "Trevor Ablett. *Mitigating distribution shift in robotic imitation learning* (PhD thesis, University of Toronto)."
)
# Stages record their method's paper in the provenance (`citation` in a stage's entry) and trainers
# in their model card's data (each trainer registers its own). FIRE runs outside both: its datasets
# and policies are cited by name.
FIRE_CITATION = "Ablett et al., *Failure identification to reduce expert burden in intervention-based learning*, 2020."


def _template(name: str) -> Template:
    return Template(resources.files("shiftkit.cards").joinpath("templates", name).read_text())


def _citation(cites: list[str | None]) -> str:
    """The methods' papers (each once, in order) and the thesis, as a Markdown list."""
    return "\n".join(f"- {c}" for c in [*dict.fromkeys(c for c in cites if c), THESIS])


def _stage_citations(provenance: dict[str, Any]) -> list[str | None]:
    """The citations the provenance records with its stages (each source's own stages first)."""
    own = [s for src in provenance.get("sources", []) for s in src.get("stages") or []]
    return [s.get("citation") for s in [*own, *provenance.get("stages", [])]]


def _fmt(values: Any, k: int = 4) -> str:
    flat = [float(v) for v in _flatten(values)]
    shown = ", ".join(f"{v:.4g}" for v in flat[:k])
    return f"[{shown}{', ...' if len(flat) > k else ''}]"


def _flatten(values: Any) -> list[Any]:
    if isinstance(values, list):
        return [x for v in values for x in _flatten(v)]
    return [values]


def shiftkit_version(versions: dict[str, Any]) -> str:
    """shiftkit's version as a provenance records it, with the commit when it ran from a checkout:
    `0.1.0 (commit 1a53137, uncommitted changes)`."""
    text = str(versions.get("shiftkit", "?"))
    commit = versions.get("shiftkit_commit")
    if commit:
        text += f" (commit {str(commit)[:7]}{', uncommitted changes' if versions.get('shiftkit_dirty') else ''})"
    return text


def _stage_lines(stages: list[dict[str, Any]], indent: str) -> list[str]:
    return [
        f"{indent}{i + 1}. `{s['name']}` v{s['version']}: `{json.dumps(s['params'], sort_keys=True)}`"
        + ("; counted: " + ", ".join(f"{k} {v}" for k, v in s["report"].items()) if s.get("report") else "")
        for i, s in enumerate(stages)
    ]


def _source_lines(sources: list[dict[str, Any]]) -> list[str]:
    """One item per source (its scalar facts), with its episode count, fps and own stages when
    the provenance records them (pipeline runs)."""
    lines = []
    for src in sources:
        facts = ", ".join(
            f"{k}: `{v}`" for k, v in src.items() if v not in (None, "") and k not in ("stages", "episodes", "fps")
        )
        line = f"- {facts}"
        if isinstance(src.get("episodes"), list):
            first, end = src["episodes"]
            line += (
                f"; {end - first} episode(s) in this dataset (episodes {first} to {end - 1}) at {src.get('fps')} fps"
            )
        lines.append(line)
        if src.get("stages"):
            lines.append("  its own stages, before the common ones:")
            lines += _stage_lines(src["stages"], "  ")
    return lines


def _quality(verdict: dict[str, Any] | None) -> str:
    """The card's quality section from the provenance's verdict (`shiftkit validate --quality`)."""
    if not verdict:
        return "No quality verdict recorded (`shiftkit validate DATASET --quality` gives one)."
    findings = verdict.get("findings", [])
    lines = [
        f"Verdict: **{verdict.get('verdict')}** ({len(findings)} finding(s) in {verdict.get('episodes')} episodes; "
        f"action chunk {verdict.get('chunk_size')} frames), from shiftkit's content checks and lerobot-doctor "
        f"{verdict.get('lerobot_doctor', {}).get('version', '?')}'s {', '.join(verdict.get('lerobot_doctor', {}).get('checks', []))} checks."
    ]
    lines += [f"- {f['severity']} `{f['check']}` ({f['by']}): {f['message']}" for f in findings]
    if verdict.get("notes"):
        lines.append(
            f"\nlerobot-doctor's {len(verdict['notes'])} heuristic warning(s) that do not count are listed in "
            "`meta/shiftkit_provenance.json` (`quality.notes`)."
        )
    return "\n".join(lines)


def render_dataset_card(root: str | Path, provenance: dict[str, Any], license: str = "apache-2.0") -> str:
    """Card for the dataset at `root` (meta/info.json, meta/stats.json) made as `provenance` says."""
    root = Path(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    stats_path = root / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text()) if stats_path.exists() else {}
    features = "\n".join(
        f"| `{k}` | {ft['dtype']} | {tuple(ft['shape'])} | {', '.join(map(str, ft['names'][:8])) + (' ...' if len(ft['names']) > 8 else '') if isinstance(ft.get('names'), list) else ''} |"
        for k, ft in info["features"].items()
    )
    stat_rows = "\n".join(
        f"| `{k}` | {_fmt(v['mean'])} | {_fmt(v['std'])} |"
        for k, v in stats.items()
        if isinstance(v, dict) and "mean" in v and k not in ("index", "episode_index", "frame_index", "task_index")
    )
    sources = "\n".join(_source_lines(provenance.get("sources", []))) or "- (none)"
    stages = "\n".join(_stage_lines(provenance.get("stages", []), "")) or "(none: the sources were converted unchanged)"
    tasks_path = root / "meta" / "tasks.parquet"
    task_list = ""
    if tasks_path.exists():
        import pandas as pd

        task_list = "\n".join(f"- `{t}`" for t in pd.read_parquet(tasks_path).index)
    stage_names = [s["name"] for s in provenance.get("stages", [])]
    cites = _stage_citations(provenance) + ([FIRE_CITATION] if "fire" in provenance else [])
    versions = provenance.get("versions", {})
    return _template("dataset_card.md").substitute(
        license=license,
        extra_tags="\n".join(f"- {n}" for n in dict.fromkeys(stage_names)),
        repo_id=provenance.get("output", {}).get("repo_id", root.name),
        shiftkit_version=shiftkit_version(versions),
        lerobot_version=versions.get("lerobot", "?"),
        episodes=info["total_episodes"],
        frames=info["total_frames"],
        fps=info["fps"],
        tasks=info["total_tasks"],
        sources=sources,
        stages=stages,
        seed=provenance.get("seed"),
        quality=_quality(provenance.get("quality")),
        features=features,
        stats=stat_rows,
        task_list=task_list,
        citation=_citation(cites),
    )


def _normalization(norm: dict[str, Any] | None) -> str:
    """The card's input-normalisation section (BC policies: `policies.bc_policy.Normalization`)."""
    if not norm:
        return ""
    clip = f"clipped to +-{norm['clip']:g} stds" if norm.get("clip") is not None else "not clipped"
    return (
        "\n## Input normalisation\n\n"
        f"`(x - mean) / std` with each dimension's std floored at max({norm['std_floor']:g} x its RMS value, "
        f"{norm['std_min']:g}); inputs {clip}, action targets never clipped. "
        f"Dimensions normalised by a floored std: {norm.get('floored_dims', '?')}.\n"
    )


def render_model_card(card: dict[str, Any]) -> str:
    """Card for a trained policy: keys `trainer`, `datasets`, `args`, `metrics`, `env`, `versions`,
    optionally `citation` (the trainer's method) and `normalization` (BC: the std floor and input
    clipping)."""
    datasets = (
        "\n".join(
            "- " + ", ".join(f"{k}: `{v}`" for k, v in d.items() if v not in (None, ""))
            for d in card.get("datasets", [])
        )
        or "- (none)"
    )
    args = "\n".join(f"| `{k}` | `{v}` |" for k, v in sorted(card.get("args", {}).items()))
    metrics = "\n".join(
        f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in card.get("metrics", {}).items()
    )
    trainer = str(card.get("trainer", "policy"))
    return _template("model_card.md").substitute(
        normalization=_normalization(card.get("normalization")),
        trainer=trainer,
        shiftkit_version=shiftkit_version(card.get("versions", {})),
        datasets=datasets,
        env=card.get("env") or "(not evaluated in an environment)",
        args=args,
        metrics=metrics or "| (none yet) | |",
        citation=_citation([card.get("citation"), FIRE_CITATION if trainer == "fire" else None]),
    )
