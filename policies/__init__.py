"""shiftkit.policies: the trainers (BC, FIRE, VPACE / LfGP) with their networks, buffers and reward models, and policy evaluation."""
