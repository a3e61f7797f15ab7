"""TorchRL's ``LossModule`` contract for the losses written here: ``in_keys``, ``out_keys`` (hence ``repr``,
``select_out_keys`` and keyword calls through ``dispatch``) and ``make_value_estimator``.

A loss that TorchRL does not already give these (one that subclasses ``LossModule`` directly) mixes in
:class:`KeyedLoss` before ``LossModule`` and implements two methods::

    class MyLoss(KeyedLoss, LossModule):
        SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)   # what make_value_estimator accepts
        default_value_estimator = ValueEstimators.TD0

        def _loss_in_keys(self):   # every key forward reads, given the current tensor_keys and options
            return [self.tensor_keys.action, *self.actor_network.in_keys, ...]

        def _loss_out_keys(self):  # every key forward returns, in a fixed order
            return ["loss_actor", "loss_qvalue", ...]

        @dispatch                  # keyword calls: loss(observation=..., next_reward=...)
        def forward(self, tensordict): ...

``set_keys`` recomputes ``in_keys``; ``select_out_keys`` narrows ``out_keys`` (``forward`` still returns every
term and TorchRL's hook drops the others). A loss whose targets are one-step and written in closed form in
``forward`` (PE-RLHF's proxy-Q) accepts ``TD0`` and takes its ``gamma``; any other estimator is refused with
:class:`UnsupportedValueEstimator`, whose message names the supported ones. The checks every such loss must
pass are in ``tests/objectives/test_loss_contract.py``: a new loss adds one entry to its ``LOSSES`` table.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from tensordict.utils import NestedKey, unravel_key
from torchrl.objectives.utils import ValueEstimators, dispatch_value_estimator

__all__ = ["KeyedLoss", "TakeoverKeys", "UnsupportedValueEstimator", "ordered_keys"]


@dataclass
class TakeoverKeys:
    """The keys :class:`~pe_rlhf.transforms.InterventionTransform` writes that every takeover loss reads (the
    agent's proposal at the root, the rest under ``next``); a loss's ``_AcceptedKeys`` extends it."""

    action: NestedKey = "action"
    behavior_action: NestedKey = ("next", "behavior_action")
    intervention: NestedKey = ("next", "intervention")
    intervention_start: NestedKey = ("next", "intervention_start")


class UnsupportedValueEstimator(ValueError, NotImplementedError):
    """``make_value_estimator`` asked for an estimator the loss cannot use. A ``ValueError`` (bad argument) and a
    ``NotImplementedError`` (what TorchRL's own losses raise), so either ``except`` catches it."""


def ordered_keys(keys: Iterable[NestedKey]) -> list[NestedKey]:
    """``keys`` unravelled (``("a",)`` -> ``"a"``, nested tuples flattened), duplicates dropped, first order kept:
    ``dispatch`` maps positional arguments onto ``in_keys`` in this order, so it must not vary between runs (a
    ``set`` of strings does, with hash randomisation)."""
    out: list[NestedKey] = []
    for key in keys:
        key = unravel_key(key)
        if key not in out:
            out.append(key)
    return out


def next_keys(keys: Iterable[NestedKey]) -> list[NestedKey]:
    """``("next", key)`` for each key (the same entries one step later)."""
    return [unravel_key(("next", key)) for key in keys]


class KeyedLoss:
    """Mixin (before ``LossModule``): lazily computed ``in_keys``/``out_keys`` with setters, and a
    ``make_value_estimator`` limited to ``SUPPORTED_VALUE_ESTIMATORS`` (module docstring)."""

    SUPPORTED_VALUE_ESTIMATORS: tuple[ValueEstimators, ...] = (ValueEstimators.TD0,)
    default_value_estimator: ValueEstimators = ValueEstimators.TD0
    _in_keys: list[NestedKey] | None = None
    _out_keys: list[str] | None = None

    def _loss_in_keys(self) -> list[NestedKey]:
        raise NotImplementedError(f"{type(self).__name__} must define _loss_in_keys()")

    def _loss_out_keys(self) -> list[str]:
        raise NotImplementedError(f"{type(self).__name__} must define _loss_out_keys()")

    def _set_in_keys(self) -> None:  # LossModule._forward_value_estimator_keys calls it after set_keys
        self._in_keys = ordered_keys(self._loss_in_keys())

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = list(values)

    @property
    def out_keys(self) -> list[str]:
        if self._out_keys is None:
            self._out_keys = list(self._loss_out_keys())
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values) -> None:
        self._out_keys = list(values)

    def check_value_type(self, value_type) -> ValueEstimators:
        """``value_type`` (an enum member or its name, ``None`` = the default) if supported, else one clear error."""
        value_type = self.default_value_estimator if value_type is None else value_type
        by_name = {v.name.lower(): v for v in ValueEstimators}  # "td0" and "TD0" as TorchRL accepts them
        coerced = by_name.get(value_type.lower(), value_type) if isinstance(value_type, str) else value_type
        if coerced not in self.SUPPORTED_VALUE_ESTIMATORS:
            supported = [v.name for v in self.SUPPORTED_VALUE_ESTIMATORS]
            name = getattr(coerced, "name", coerced)
            raise UnsupportedValueEstimator(
                f"{type(self).__name__}.make_value_estimator: value_type={name!r} is not supported; "
                f"allowed: {supported}")
        return coerced

    def make_value_estimator(self, value_type: ValueEstimators | str | None = None, **hyperparams):
        """Build the estimator (one of ``SUPPORTED_VALUE_ESTIMATORS``); a ``gamma`` given here becomes the loss's
        ``gamma``. Returns the loss (TorchRL's chaining)."""
        value_type = self.check_value_type(value_type)
        if "gamma" in hyperparams and hasattr(self, "gamma"):
            self.gamma = float(hyperparams["gamma"])
        keys = {name: getattr(self.tensor_keys, name) for name in ("reward", "done", "terminated")
                if hasattr(self.tensor_keys, name)}
        dispatch_value_estimator(self, value_type, supported=self.SUPPORTED_VALUE_ESTIMATORS,
                                 tensor_keys=keys, **hyperparams)
        return self
