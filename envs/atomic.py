"""All or nothing: a call that changes an env either completes or leaves the env exactly as it was.

An env that follows the rule (the driver, envs/core.py; the focal-only env, envs/focal.py) works a
call out in locals and replaces its committed attributes at the end, in one ``_commit``; it never
writes into them. So a failed call has nothing to undo but what it could not help changing: the
generators it drew from, and caches such as the renderer's. ``AllOrNothing`` is the mixin that
puts those back:

    class MyEnv(AllOrNothing):
        _committed = {"state": "_state", "seed": "seed"}   # what _commit(state=..., seed=...) replaces
        def _generators(self): return [self.generator]      # whose states a failed call puts back

        @one_at_a_time
        def step(self, actions):
            with self.kept():                                # anything raising in here changes nothing
                state = ...
                self._commit(state=state)

``kept()`` is public for a wrapper whose one call is a call of this env and then code of its own
(FocalEnv: the driver's reset, then the bots' reset): if the wrapper's part raises after the env
committed, the env is put back too.
"""
from __future__ import annotations

import contextlib
import functools

import torch


def one_at_a_time(method):
    """A call that changes the env: one at a time (two steps from two threads at once read the same
    state and one of them was lost, silently), under the env's ``_lock`` (an RLock, as calls nest)."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return call


def env_call(method):
    """A call of the env's public API: one at a time (see one_at_a_time), outside
    torch.inference_mode() and without grad (in this order: inference_mode(False) turns grad on).
    Inference mode makes inference tensors, which nothing may write into outside it: an env reset
    under it failed every later call outside it in the renderer's buffers. So what the env keeps
    and returns are normal tensors, whatever mode the caller is in."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._lock, torch.inference_mode(False), torch.no_grad():
            return method(self, *args, **kwargs)
    return call


class AllOrNothing:
    """The mixin of an env whose calls are all or nothing; see the module docstring. The env holds an
    RLock in ``_lock`` and names, in ``_committed``, the attributes its calls replace at their end
    ({keyword of _commit: attribute}); ``_generators()`` are the generators its calls draw from, and
    ``_save_more()`` / ``_restore_more(saved)`` put back what else a failed call may have touched."""

    _committed: dict = {}
    _running_hooks = False  # see _all_or_nothing

    def _generators(self) -> list:
        return []

    def _save_more(self):
        """What else a failed call must put back, saved when kept() begins (e.g. a mutable part's
        snapshot); _restore_more(saved) gets it back."""
        return None

    def _restore_more(self, saved) -> None:
        """After a failed call's committed attributes and generators were put back: the rest (the
        driver: its renderer's caches)."""

    def _commit(self, **values) -> None:
        """Replace the committed attributes (each keyword one of _committed's): the end of a call."""
        for key, value in values.items():
            setattr(self, self._committed[key], value)

    @contextlib.contextmanager
    def kept(self):
        """The env as it is now, put back if the block raises: its committed attributes (replaced,
        never written into, so holding them keeps them) and its generators' states. The lock is held
        throughout, so no other call comes between."""
        with self._lock:
            committed = {key: getattr(self, attribute) for key, attribute in self._committed.items()}
            rngs = [generator.get_state() for generator in self._generators()]
            more = self._save_more()
            try:
                yield
            except BaseException:
                self._commit(**committed)
                for generator, rng in zip(self._generators(), rngs, strict=True):
                    generator.set_state(rng)
                self._restore_more(more)
                raise

    # ------------------------------------------------------------------ an env that runs a task's hooks
    def _hooks_owner(self) -> str:
        """The name the messages below give the hooks' owner (the driver: its scenario's class)."""
        return type(self).__name__

    def _held(self) -> dict:
        """{name: tensor} of the committed tensors the hooks are handed (written into in place, they
        could not be put back)."""
        return {}

    @contextlib.contextmanager
    def _all_or_nothing(self):
        """A call that runs the env's hooks: kept(), refused when a hook makes it (_refuse_reentry), and
        a RuntimeError (the env then needs a reset) where a hook wrote into a held tensor in place and
        the call failed: that write cannot be undone."""
        self._refuse_reentry()
        held = self._held()
        versions = [_version(tensor) for tensor in held.values()]
        self._running_hooks = True
        try:
            with self.kept():
                yield
        except BaseException as error:
            written = [name for (name, tensor), version in zip(held.items(), versions, strict=True)
                       if _version(tensor) != version]
            if written:  # a hook broke the contract: what it wrote cannot be undone
                self._needs_reset = True
                raise RuntimeError(f"a hook of {self._hooks_owner()} wrote into the env's state in place "
                                   f"({', '.join(written)}) and the call failed, so it cannot be undone: call reset(); "
                                   f"hooks must return new tensors, never write into the state they are given"
                                   ) from error
            raise
        finally:
            self._running_hooks = False

    def _refuse_reentry(self) -> None:
        """A call that changes the env, made by one of its hooks (the same thread: others wait for the
        lock), is refused: the outer call would commit over what it did, or run on with the renderer closed."""
        if self._running_hooks:
            raise RuntimeError(f"a hook of {self._hooks_owner()} called the env's step, reset, reset_worlds, "
                               f"reset_to_level, set_state or close while the env ran its hooks: hooks must not "
                               f"call the env (they get the state and return new values)")


def _version(tensor: torch.Tensor) -> int | None:
    """The count of in-place writes into `tensor` (None for inference tensors, which keep none)."""
    return None if tensor.is_inference() else tensor._version
