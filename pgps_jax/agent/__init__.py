"""The algorithm: PGPS (`pgps`) and its parts, each a small pure module.

`config` (the paper's hyper-parameters), `cem` (the search distribution), `td3` (the
actor-critic and the guided loss), `qfilter` (Algorithm 2), `buffer` (the device replay
buffer), `networks`, `rollout` (episodes of a batch of actors), `evaluation` (the test
episodes of Section 5.1) and `metrics` (what a generation reports).
"""
