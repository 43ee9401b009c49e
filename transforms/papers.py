"""The papers the stages' methods come from (thesis chapters 3, 4 and 7), as the stages' `citation`s."""

MULTIVIEW = "Ablett et al., *Seeing all the angles: learning multiview manipulation policies for contact-rich tasks from demonstrations*, IROS 2021."
FORCE_MATCHING = "Ablett et al., *Multimodal and force-matched imitation learning with a see-through visuotactile sensor*, IEEE T-RO 2025."
VPACE = "Ablett et al., *Efficient imitation without demonstrations via value-penalized auxiliary control from examples*, ICRA 2025."
