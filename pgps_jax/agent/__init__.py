"""The algorithm: PGPS (`pgps`), its parts, each a small pure module, and the baselines built
from them.

`config` (the paper's hyper-parameters and the baselines' presets), `base` (the `TrainState`
and the interface every algorithm shares), `couplings` (PGPS's couplings switched per
state), `cem` (the search distribution), `td3` (the
actor-critic and the guided loss), `qfilter` (Algorithm 2), `buffer` (the device replay
buffer), `networks`, `rollout` (episodes of a batch of actors), `evaluation` (the test
episodes of Section 5.1), `metrics` (what a generation reports), `baselines` (CEM alone, TD3
alone, CEM-RL) and `algorithms` (each by name).
"""
