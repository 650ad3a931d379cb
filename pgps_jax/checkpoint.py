"""Checkpoints of a training run with orbax-checkpoint: the whole TrainState plus host metadata.

A checkpoint is the directory `<run>/checkpoints/<generation>/` holding
- `state`: the full TrainState (CEM, TD3 and optimiser states, the replay buffer, β, counters
  and the PRNG key), so a resumed run continues bit for bit;
- `meta`: JSON with the resolved configuration it was produced with, the generation and env
  steps, the wall time so far and the byte sizes of the CSV logs at that moment.

orbax writes each checkpoint into a temporary directory and renames it when complete, so a
process killed mid-save leaves no half-written checkpoint: the temporary directory is never
listed as a step and is removed when the run directory is opened again. Saves are synchronous
(the next generation donates the state's buffers). Host-side; never called inside jit.
"""

import pathlib
from typing import Any, Optional

import jax
import orbax.checkpoint as ocp


class Checkpoints:
    """The checkpoints of one run directory, keeping the most recent `keep`."""

    def __init__(self, directory: pathlib.Path, keep: int = 3):
        options = ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=True, enable_async_checkpointing=False,
            cleanup_tmp_directories=True)
        self.directory = pathlib.Path(directory).absolute()
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def steps(self) -> list[int]:
        """Generations that have a complete checkpoint, ascending."""
        return sorted(self._manager.all_steps())

    def latest_step(self) -> Optional[int]:
        """The most recent complete checkpoint's generation, or None."""
        return self._manager.latest_step()

    def save(self, step: int, state: Any, meta: dict) -> None:
        """Writes checkpoint `step` (a generation) atomically and waits until it is on disk."""
        self._manager.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)), force=True)
        self._manager.wait_until_finished()

    def meta(self, step: int) -> dict:
        """The metadata of checkpoint `step`."""
        restored = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        return restored.meta

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict]:
        """(state, meta) of checkpoint `step`; `abstract_state` gives the tree, shapes, dtypes
        (e.g. `jax.eval_shape` of the init function)."""
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
        restored = self._manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()))
        return restored.state, restored.meta

    def close(self) -> None:
        self._manager.close()
