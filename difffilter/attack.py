"""The attacker inside the loop: a step object on one of three channels.

An attack is data plus a step. At measurement ``k`` of the loop
(:func:`difffilter.loop.closed_loop`) it reads what its threat model allows — the true
measurement ``y_k``, the true state ``x_k``, the commanded input ``u_{k−1}`` and, for an
adaptive attacker, the estimator's output of the previous step (``view``) — and returns
what it injects and where (an actuator attack acts on the transition to ``x_k``, so it
steps before it: it reads ``x_{k−1}`` and no measurement)::

    A_0            = attack.init(batch_shape, T, dim, generator, dtype=, device=)
    A_k, a_k, l_k  = attack.step(A_{k−1}, k, y=y_k, x=x_k, u=u_{k−1}, view=out_{k−1})

with ``a_k [..., dim]`` the value and ``l_k`` the flag (``[...]``, or ``[..., dim]`` per
entry). The channel says what it acts on (:class:`Channel`)::

    SENSOR        ỹ_k = y_k + l_k a_k                  (additive false data)
    REPLACEMENT   ỹ_k = a_k where l_k, y_k elsewhere   (deception, replay)
    ACTUATOR      ũ_{k−1} = u_{k−1} + l_k a_k          (the plant is driven with ũ; the
                                                        estimator knows only u)

An actuator attack may also write the sensors to hide what it does (a *covert* attack,
Smith 2015; :attr:`Attack.conceals`): after the measurement the loop asks it for a
correction ``c_k [..., dy]`` and hands the estimator ``ỹ_k = y_k + c_k``::

    A_k, c_k = attack.conceal(A_k, k, y=y_k, x=x_k)          (only if attack.conceals)

An attack that reads nothing (a bias, a ramp, a known signal, a random replacement)
derives from :class:`TabulatedAttack`: ``init`` draws the whole table ``[..., T, dim]``
at once (the same random numbers as a vectorised simulation), and the step reads row
``k``, so open-loop speed is kept. What the loop records as the injected attack is the
change it made, ``ỹ_k − y_k`` on the sensor side and ``l_k a_k`` on the actuator side;
``values`` (``Trajectories.info["attack_values"]``) are the ``a_k`` at every step, also
where they were not injected. An estimator never reads an attack object: what it assumes
about attacks is its own parameter.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ._checks import Choice

__all__ = ["Channel", "Attack", "TabulatedAttack", "attack_dim", "inject", "same_side"]


class Channel(Choice):
    """What an attack acts on (module docstring)."""

    SENSOR = "sensor"
    REPLACEMENT = "replacement"
    ACTUATOR = "actuator"


def same_side(a: Channel | str, b: Channel | str) -> bool:
    """Whether two channels act on the same side of the plant: the measurements (sensor
    and replacement attacks, both recorded as ``ỹ − y``) or the inputs (actuator attacks,
    recorded as ``ũ − u``). An attack estimate is compared only with an attack on its side:
    a sensor estimate against an actuator signal is a comparison of two different
    quantities, whatever their shapes."""
    return (Channel(a) is Channel.ACTUATOR) == (Channel(b) is Channel.ACTUATOR)


def attack_dim(model, channel: Channel | str) -> int:
    """The entries an attack on ``channel`` takes in ``model`` (its ``dim`` at ``init``, the
    width of its recorded signal): the inputs (``dim_u``) on the actuators, else the
    measurements (``dim_y``)."""
    return model.dim_u if Channel(channel) is Channel.ACTUATOR else model.dim_y


class Attack:
    """Base of every attack (module docstring). Subclasses set :attr:`channel` and
    implement :meth:`init` and :meth:`step`; an adaptive attack (one that reads the
    estimator's last output) sets :attr:`reads_view`.

    :attr:`reads_state` declares whether the attack reads the true state ``x`` (an insider,
    or an attacker with a perfect model of the plant: from ``x_k`` and ``y_k`` it knows the
    measurement noise exactly, and a trial's attack that subtracted it carried twice the
    bias with fewer χ² alarms than no attack at all). ``True`` by default, so that an attack
    of one's own keeps reading ``x``; an attack that sets it ``False`` (a network attacker:
    what it intercepts, ``y`` and ``u``) gets ``x=None``, and the robustness report lists
    which threats read the state. The library's tabulated attacks and ``Replay`` read no
    state; ``Covert`` does (its copies start from it)."""

    channel: Channel = Channel.SENSOR
    reads_view: bool = False
    reads_state: bool = True
    conceals: bool = False

    def init(
        self, batch_shape, num_steps: int, dim: int, generator=None, *, dtype, device=None
    ) -> Any:
        """The attacker's state before step 1 of ``num_steps`` on ``dim`` channels."""
        raise NotImplementedError

    def step(self, state, k: int, *, y=None, x=None, u=None, view=None):
        """``(state, value [..., dim], flag [...] or [..., dim])`` at measurement ``k``.

        The flag's rank says what it flags: one rank less than the value's full shape
        ``[..., dim]`` is per run, the same rank per entry; both broadcast over the runs. A
        value ``[dim]`` is one for every run, but a flag ``[dim]`` is per run (a batch of
        ``dim`` runs takes it so; another is refused): a flag per entry for every run is
        ``[1, dim]``."""
        raise NotImplementedError

    def last_step(self, state) -> int | None:
        """The last measurement ``k`` that ``state`` (from :meth:`init`) can step, or ``None``
        where it has no end (the default). A loop that would run past it is refused before
        its first step, naming its ``horizon``."""
        return None

    def conceal(self, state, k: int, *, y, x):
        """``(state, c_k [..., dy])``: what an actuator attack that :attr:`conceals` adds to
        the measurement ``y_k`` (module docstring); never called otherwise."""
        raise NotImplementedError


class TabulatedAttack(Attack):
    """An attack that reads nothing: ``init`` tabulates ``sample``'s ``(values [*, T, dim],
    flags [*, T] or [*, T, dim])``, and step ``k`` reads row ``k − 1``.

    Subclasses implement ``sample(batch_shape, num_steps, dim, generator, *, dtype,
    device) -> (values, flags)`` (:meth:`sample`).
    """

    reads_state = False  # (it reads nothing at all)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        """The whole attack at once: ``(values, flags)``.

        Args:
            batch_shape: the runs' batch shape ``*batch`` (an int or a tuple).
            num_steps: ``T``, the measurements ``k = 1 … T``; row ``t`` is ``k = t + 1``.
            dim: the channel's width (``dy`` on the sensors, ``du`` on the actuators).
            generator: the only source of random draws (the loop's ``"attack"`` stream).
            dtype, device: of ``values``.

        Returns:
            ``values [*batch, T, dim]``: what the attacker would inject at every step
            (also where it does not), and ``flags [*batch, T]`` (bool; or ``[*batch, T,
            dim]``, per entry): where it does. The loop applies them on :attr:`channel`
            (:func:`inject`).
        """
        raise NotImplementedError

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        values, flags = self.sample(batch_shape, num_steps, dim, generator, dtype=dtype,
                                    device=device)  # fmt: skip
        _check_tables(type(self).__name__, values, flags, batch_shape, num_steps, dim)
        return values, flags.bool()

    def last_step(self, state) -> int:
        """The tables' rows: ``num_steps`` of :meth:`init`."""
        return state[0].shape[-2]

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        values, flags = state
        flag = flags[..., k - 1, :] if flags.dim() == values.dim() else flags[..., k - 1]
        return state, values[..., k - 1, :], flag


def _check_tables(name: str, values, flags, batch_shape, num_steps: int, dim: int) -> None:
    """``ValueError`` unless ``sample`` returned ``values [*batch, T, dim]`` and ``flags
    [*batch, T]`` or ``[*batch, T, dim]`` (:meth:`TabulatedAttack.sample`). A table of one
    value for every run (``[T, dim]``) beside flags per run (``[B, T]``) had been read with
    the flags' rows as steps: every run flagged where run ``k − 1`` was."""
    batch = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
    rows = (*batch, num_steps)
    if not isinstance(values, Tensor) or tuple(values.shape) != (*rows, dim):
        got = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(
            f"{name}.sample must return values [*batch, T, dim] = {list((*rows, dim))} (expand "
            f"a table shared by the runs); got {got}"
        )
    if not isinstance(flags, Tensor) or tuple(flags.shape) not in (rows, (*rows, dim)):
        got = tuple(flags.shape) if isinstance(flags, Tensor) else type(flags).__name__
        raise ValueError(
            f"{name}.sample must return flags [*batch, T] = {list(rows)} (per run) or "
            f"[*batch, T, dim] = {list((*rows, dim))} (per entry); got {got}"
        )


def _entrywise(flag: Tensor, signal: Tensor, value: Tensor) -> Tensor:
    """A flag ``[...]`` (per run) or ``[..., d]`` (per entry) as ``[..., d]``-broadcastable:
    per entry where its rank is that of the full shape of ``signal`` and ``value`` together
    (a value ``[d]`` shared by the runs beside per-run flags ``[B]``, B = d, had had those
    flags read per entry)."""
    full = len(torch.broadcast_shapes(signal.shape, value.shape))
    return flag if flag.dim() == full else flag.unsqueeze(-1)


def inject(channel: Channel, signal: Tensor, value: Tensor, flag: Tensor) -> tuple[Tensor, Tensor]:
    """``(attacked signal, recorded attack)`` of one step on ``channel`` (module docstring):
    ``signal [..., d]`` (``y_k`` or ``u_{k−1}``), ``value [..., d]``, ``flag`` → both ``[..., d]``.
    The flag's rank says what it flags (:meth:`Attack.step`): one less than the full shape
    of ``signal`` and ``value`` per run, the same per entry."""
    f = _entrywise(flag, signal, value)
    if channel is Channel.REPLACEMENT:
        received = torch.where(f, value, signal)
        return received, torch.where(f, received - signal, torch.zeros_like(signal))
    # where, not f · value: an unflagged non-finite value is not injected (0 · inf = NaN)
    change = torch.where(f, value, torch.zeros_like(value))
    return signal + change, change
