"""Baselines built from PGPS's parts (its networks, CEM, TD3 updates, buffer, rollouts and
test evaluation), each with its published hyper-parameters (`config.algorithm_preset`):
`CEMAlone` (the population's search, no critic), `TD3Alone` (one exploring actor) and `CEMRL`
(Pourchot & Sigaud, 2019: half the population trained by a shared critic)."""
