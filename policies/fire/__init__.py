"""FIRE (thesis ch. 5, docs/fire.md): failure prediction and intervention, one folder.

`loop` runs Algorithm 2 in simulation (`shiftkit fire`) with its settings (`config`), one episode
(`episode`), the BC updates (`learning`) and the episode files (`recording`); `discriminator`,
`failure_predictors` and `oracle` (the simulated person) are its parts; `aggregate` is offline FIRE
over DAgger-layout recordings (`dagger_recording`, `shiftkit fire aggregate`) with its fitted
predictor (`predictor`); `runs` reads finished runs back (plots, studies). Nothing is imported here,
so `shiftkit fire aggregate --help` loads no torch."""
