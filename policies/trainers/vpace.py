"""Trainers `vpace` and `lfgp`: scheduled auxiliary control from success examples or expert
trajectories (`policies/vpace.py`; CLI glue in `policies/vpace_cli.py`)."""

from __future__ import annotations

from shiftkit.policies.trainers import Trainer, register

for _name, _help, _citation in (
    (
        "vpace",
        "VPACE / ACE / SQIL / DAC / RCE from success examples",
        "Ablett et al., *Efficient imitation without demonstrations via value-penalized auxiliary control "
        "from examples*, ICRA 2025.",
    ),
    (
        "lfgp",
        "Learning from Guided Play (expert trajectories, per-task DAC)",
        "Ablett et al., *Learning from guided play: improving exploration for adversarial imitation learning "
        "with simple auxiliary tasks*, RA-L 2023.",
    ),
):
    register(
        Trainer(
            name=_name,
            help=_help,
            args="shiftkit.policies.vpace:VPACEArgs",
            cli="shiftkit.policies.vpace_cli",
            load_policy="shiftkit.policies.vpace:load_policy",
            citation=_citation,
        )
    )
