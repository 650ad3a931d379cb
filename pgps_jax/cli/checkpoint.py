"""Checkpoints of a training run with orbax-checkpoint: the whole TrainState plus host metadata.

A checkpoint is the directory `<run>/checkpoints/<generation>/` holding
- `state`: every leaf of the TrainState (CEM, TD3 and optimiser states, the replay buffer, β,
  counters, PRNG keys, the env states of test episodes under way), so a resumed run continues
  bit for bit;
- `meta`: JSON with the resolved configuration it was produced with, the generation and env
  steps, the wall time so far, the byte sizes of the CSV logs at that moment, the state's
  layout (path, shape and dtype of every leaf) and a SHA-256 checksum of its contents.

The state is fetched to the host once; orbax stores its leaves under their index in the
flattened tree. Leaves orbax cannot store as they are keep their content all the same: a
zero-size array (MJX's `act` on tasks without actuator state) is all shape and dtype, which
the layout records; a typed PRNG key is stored as its key data and wrapped again on restore.

orbax writes each checkpoint into a temporary directory and renames it when complete, so a
process killed mid-save leaves no half-written checkpoint. A save that fails (disk full, I/O
error) removes its temporary directory and raises `WriteFailed`. A restore checks the layout
against the state the run expects, orbax's own reading and the checksum; `restore_latest`
sets a damaged checkpoint aside (renamed into `<run>/damaged_checkpoints/`, never deleted),
warns, and falls back to the next newest. Saves are synchronous (the next generation donates
the state's buffers). Host-side; never called inside jit.
"""

import contextlib
import hashlib
import math
import os
import pathlib
import shutil
import sys
import time
from typing import Any, Optional

import jax
import numpy as np
import orbax.checkpoint as ocp

from pgps_jax.cli.errors import UsageError, WriteFailed, first_line

DAMAGED = "damaged_checkpoints"
"""Where damaged checkpoints are moved, beside `checkpoints/` in the run directory."""


class DamagedCheckpoint(Exception):
    """A checkpoint whose files cannot be read or whose contents fail the checksum."""


def _is_key(leaf: Any) -> bool:
    return jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def layout(tree: Any) -> list[dict]:
    """Path, shape and dtype of each leaf of `tree` (arrays or ShapeDtypeStructs), in order;
    typed PRNG key arrays also name their implementation."""
    entries = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        entry = {"path": jax.tree_util.keystr(path), "shape": list(leaf.shape),
                 "dtype": str(leaf.dtype)}
        if _is_key(leaf) and isinstance(leaf, jax.Array):
            entry["key_impl"] = str(jax.random.key_impl(leaf))
        entries.append(entry)
    return entries


def checksum(leaves: list[np.ndarray]) -> str:
    """SHA-256 over the leaves' dtypes, shapes and bytes, in order."""
    digest = hashlib.sha256()
    for leaf in leaves:
        digest.update(f"{leaf.dtype}{leaf.shape}".encode())
        digest.update(np.ascontiguousarray(leaf).data)
    return digest.hexdigest()


def _host_leaves(state: Any) -> list[np.ndarray]:
    """The state's leaves on the host (typed keys as their key data), in one transfer."""
    leaves = [jax.random.key_data(x) if _is_key(x) else x for x in jax.tree.leaves(state)]
    return [np.asarray(x) for x in jax.device_get(leaves)]


def due(generation: int, every: Optional[int], every_s: Optional[float],
        since_s: float) -> bool:
    """Whether a checkpoint is due after `generation`, `since_s` seconds after the last one:
    every `every` generations and every `every_s` seconds, each where set (None: not by it)."""
    return bool(every and generation % every == 0
                or every_s is not None and since_s >= every_s)


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
        """Writes checkpoint `step` (a generation) atomically and waits until it is on disk;
        raises WriteFailed (its temporary files removed) if it cannot."""
        leaves = _host_leaves(state)
        meta = {**meta, "layout": layout(state), "checksum": checksum(leaves)}
        stored = {f"{i:05d}": leaf for i, leaf in enumerate(leaves) if leaf.size}
        try:
            with _stderr_shown_on_success():
                self._manager.save(step, args=ocp.args.Composite(
                    state=ocp.args.StandardSave(stored), meta=ocp.args.JsonSave(meta)),
                    force=True)
                self._manager.wait_until_finished()
        except Exception as e:
            self._remove_partial(step)
            self._manager.reload()
            raise WriteFailed(self.directory / str(step), e) from None

    def _remove_partial(self, step: int, attempts: int = 50) -> None:
        """Removes what a failed save of `step` left. The writes of the save's other items may
        still be under way when one fails, and recreate files while they are removed: waits
        for them, then removes until nothing is left."""
        try:
            self._manager.wait_until_finished()
        except Exception:  # the save's own failure, already being reported
            pass
        for _ in range(attempts):
            partial = list(self.directory.glob(f"{step}.orbax-checkpoint-tmp*"))
            if not partial:
                return
            for path in partial:
                shutil.rmtree(path, ignore_errors=True)
            time.sleep(0.02)

    def meta(self, step: int) -> dict:
        """The metadata that was saved with checkpoint `step`; DamagedCheckpoint if it cannot be
        read."""
        return _without_integrity(self._stored_meta(step))

    def _stored_meta(self, step: int) -> dict:
        """The metadata of checkpoint `step` with its layout and checksum."""
        try:
            restored = self._manager.restore(
                step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except (ValueError, OSError, KeyError) as e:
            raise DamagedCheckpoint(f"its metadata cannot be read ({first_line(e)})") from None
        if not isinstance(restored.meta, dict) or "checksum" not in restored.meta:
            raise DamagedCheckpoint("its metadata is incomplete")
        return restored.meta

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict]:
        """(state, meta) of checkpoint `step`, verified; `abstract_state` gives the tree, shapes
        and dtypes (e.g. `jax.eval_shape` of the init function).

        Raises UsageError if the checkpoint holds a differently shaped state (another
        configuration or version), DamagedCheckpoint if its files are unreadable or its
        contents fail the checksum.
        """
        meta = self._stored_meta(step)
        expected = layout(abstract_state)
        saved = meta["layout"]
        if [{k: e[k] for k in ("path", "shape", "dtype")} for e in saved] != expected:
            raise UsageError(f"checkpoint {self.directory / str(step)} holds a state of another "
                             f"layout than this run's: {_layout_mismatch(saved, expected)}")
        abstract_leaves, treedef = jax.tree.flatten(abstract_state)
        stored_shapes = [_stored_shape(e) for e in saved]
        wanted = {f"{i:05d}": np.empty(shape, dtype)
                  for i, (shape, dtype) in enumerate(stored_shapes) if math.prod(shape)}
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(wanted)))
        except (ValueError, OSError, KeyError) as e:
            raise DamagedCheckpoint(f"its state cannot be read ({first_line(e)})") from None
        leaves = [np.asarray(restored.state[f"{i:05d}"]) if math.prod(shape)
                  else np.empty(shape, dtype) for i, (shape, dtype) in enumerate(stored_shapes)]
        if checksum(leaves) != meta["checksum"]:
            raise DamagedCheckpoint("its state does not match the checksum written with it")
        state = [jax.random.wrap_key_data(leaf, impl=entry["key_impl"]) if "key_impl" in entry
                 else leaf for leaf, entry in zip(leaves, saved)]
        state = [jax.device_put(leaf, getattr(a, "sharding", None))
                 for leaf, a in zip(state, abstract_leaves)]
        return jax.tree.unflatten(treedef, state), _without_integrity(meta)

    def set_aside(self, step: int, reason: str) -> pathlib.Path:
        """Moves checkpoint `step` into `<run>/damaged_checkpoints/` and warns; returns where."""
        target_dir = self.directory.parent / DAMAGED
        target_dir.mkdir(exist_ok=True)
        target = target_dir / str(step)
        if target.exists():
            target = target_dir / f"{step}-{time.strftime('%Y%m%dT%H%M%S')}"
        (self.directory / str(step)).rename(target)
        self._manager.reload()
        print(f"warning: checkpoint {self.directory / str(step)} is damaged: {reason}; "
              f"moved to {target}", file=sys.stderr)
        return target

    def latest_meta(self) -> tuple[int, dict]:
        """(generation, metadata) of the newest checkpoint whose metadata reads; damaged ones
        are set aside. UsageError if none is left."""
        for step in reversed(self.steps()):
            try:
                return step, self.meta(step)
            except DamagedCheckpoint as e:
                self.set_aside(step, str(e))
        raise UsageError(self._none_left())

    def restore_latest(self, abstract_state: Any) -> tuple[int, Any, dict]:
        """(generation, state, meta) of the newest checkpoint that verifies; damaged ones are
        set aside. UsageError if none verifies."""
        for step in reversed(self.steps()):
            try:
                return (step, *self.restore(step, abstract_state))
            except DamagedCheckpoint as e:
                self.set_aside(step, str(e))
        raise UsageError(self._none_left())

    def _none_left(self) -> str:
        return (f"no checkpoint in {self.directory} can be restored (damaged ones are in "
                f"{self.directory.parent / DAMAGED}); start a new run in another run_dir")

    def close(self) -> None:
        self._manager.close()


@contextlib.contextmanager
def _stderr_shown_on_success():
    """Holds back what is written to stderr (file descriptor 2) inside, in memory, and writes it
    out if the block succeeds. A failed orbax save logs each failing thread's traceback there,
    and its writes still in flight print more as they end (waited for until it has been quiet
    for `_QUIET_S`); the caller reports the failure in one line instead."""
    sys.stderr.flush()
    held, saved = os.memfd_create("stderr"), os.dup(2)
    os.dup2(held, 2)
    succeeded = False
    try:
        yield
        succeeded = True
    finally:
        if not succeeded:
            _wait_until_quiet(held)
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)
        if succeeded:
            os.lseek(held, 0, os.SEEK_SET)
            while chunk := os.read(held, 1 << 16):
                os.write(2, chunk)
        os.close(held)


_QUIET_S, _QUIET_MAX_S = 0.5, 10.0


def _wait_until_quiet(fd: int) -> None:
    """Waits until nothing has been written to `fd` for `_QUIET_S` (at most `_QUIET_MAX_S`)."""
    deadline, size = time.monotonic() + _QUIET_MAX_S, -1
    while time.monotonic() < deadline and os.fstat(fd).st_size != size:
        size = os.fstat(fd).st_size
        time.sleep(_QUIET_S)


_INTEGRITY = ("layout", "checksum")


def _without_integrity(meta: dict) -> dict:
    return {k: v for k, v in meta.items() if k not in _INTEGRITY}


def _stored_shape(entry: dict) -> tuple[tuple, np.dtype]:
    """Shape and dtype in which a leaf of the layout is stored (keys as uint32 key data)."""
    if "key_impl" in entry:
        data = jax.eval_shape(lambda: jax.random.key_data(jax.random.key(0, impl=entry["key_impl"])))
        return tuple(entry["shape"]) + data.shape, data.dtype
    return tuple(entry["shape"]), np.dtype(entry["dtype"])


def _layout_mismatch(saved: list[dict], expected: list[dict]) -> str:
    """The first leaf in which a checkpoint's layout differs from the expected one, and why."""
    if len(saved) != len(expected):
        return (f"{len(saved)} leaves, this run has {len(expected)}; it was written by another "
                "configuration or version")
    for s, e in zip(saved, expected):
        if s["path"] != e["path"] or s["shape"] != e["shape"] or s["dtype"] != e["dtype"]:
            found = (f"{s['path']} {s['dtype']}{s['shape']}, this run has "
                     f"{e['path']} {e['dtype']}{e['shape']}")
            if s["path"] == e["path"] and {_key_kind(s), _key_kind(e)} == {"typed", "raw"}:
                return (f"{found}: the checkpoint holds {_key_kind(s)} PRNG keys where the "
                        f"template has {_key_kind(e)} ones. Make the template with the keys the "
                        "run was started with (jax.random.key(seed) for typed keys, "
                        "jax.random.PRNGKey(seed) for raw ones)")
            return f"{found}; it was written by another configuration or version"
    return "no difference"


def _key_kind(entry: dict) -> str:
    """"typed" for a typed PRNG key's layout entry, "raw" for a raw uint32[2] key's."""
    if entry["dtype"].startswith("key<"):
        return "typed"
    return "raw" if entry["dtype"] == "uint32" and entry["shape"][-1:] == [2] else "other"
