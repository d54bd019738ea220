"""The DQN's optimiser: Adam (or the thesis's RMSprop), with Adam's fused kernel where it runs.

PyTorch's Adam updates the parameters one tensor at a time on the CPU unless told
otherwise (its ``foreach`` path is the default on GPUs only); ``fused=True`` runs one
kernel for all of them, on the CPU as on a GPU. It is the same algorithm -- the same
moments, bias corrections and step -- computed in another order, so its numbers agree
with the single-tensor path to float rounding, not bit for bit. On the CPU it takes a
fifth off a gradient step of the features network and a tenth off one of the image
network (:doc:`/recipes`, "Beside Stable-Baselines3").

It is opt-in (``fused=None`` or ``True`` here, ``optim.fused=auto`` in the recipe): a
training run is chaotic, so rounding differently gives each seed another run, and the
default path keeps every published run -- and ``make train``'s printed result --
reproducible bit for bit.

:func:`dqn_optimizer` builds what :class:`~torchrl_causal.training.DQNLoop` uses by
default and what the recipe's ``optim`` group names.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

#: Optimisers :func:`dqn_optimizer` builds (``optim.name`` in the recipe).
OPTIMIZERS = ("adam", "rmsprop")


def fused_supported(params: Iterable[torch.Tensor]) -> bool:
    """Whether Adam's fused kernel takes these parameters: all floating point, on a device
    type PyTorch has fused optimiser kernels for (the CPU among them). A lazy module's
    parameters count by the dtype and device they will be materialised with.

    Example:
        >>> import torch
        >>> from torchrl_causal.training import fused_supported
        >>> fused_supported(torch.nn.Linear(3, 2).parameters())
        True
        >>> fused_supported([torch.zeros(2, dtype=torch.long)])
        False
    """
    from torch.utils._foreach_utils import _get_fused_kernels_supported_devices

    devices = _get_fused_kernels_supported_devices()
    params = list(params)
    # dtype / device attributes, not torch.is_floating_point: a lazy module's parameters are
    # still uninitialised here, and they refuse every torch function until materialised
    return bool(params) and all(p.dtype.is_floating_point and p.device.type in devices
                                for p in params)


def dqn_optimizer(params: Iterable[torch.Tensor], name: str = "adam", *, lr: float = 3e-4,
                  eps: float = 1e-8, alpha: float = 0.99,
                  fused: bool | None = False) -> torch.optim.Optimizer:
    """The optimiser of a DQN's parameters.

    Args:
        params: the parameters (e.g. ``loss.parameters()``; frozen ones are kept out by
            the caller or carry no gradient).
        name: ``"adam"`` (:class:`torch.optim.Adam`) or ``"rmsprop"``
            (:class:`torch.optim.RMSprop`, the thesis's).
        lr: learning rate (> 0).
        eps: the denominator's epsilon.
        alpha: RMSprop's smoothing constant (ignored by Adam).
        fused: Adam's fused kernel. ``False`` (default): PyTorch's default path;
            ``None``: the kernel where :func:`fused_supported`; ``True``: required (a
            clear error where it cannot run). RMSprop has no fused kernel: ``True`` is
            refused, ``None`` means off.

    Returns:
        The optimiser.

    Raises:
        ValueError: an unknown ``name``, ``lr`` <= 0, ``fused`` not a bool or None, or
            ``fused=True`` where the kernel cannot run (RMSprop, or parameters it does
            not take), each naming the value.

    Example:
        >>> import torch
        >>> from torchrl_causal.training import dqn_optimizer
        >>> net = torch.nn.Linear(9, 8)
        >>> opt = dqn_optimizer(net.parameters(), lr=1e-3, fused=None)  # where it runs
        >>> type(opt).__name__, opt.defaults["fused"]
        ('Adam', True)
        >>> dqn_optimizer(net.parameters(), lr=1e-3).defaults["fused"] is None  # default path
        True
        >>> dqn_optimizer(net.parameters(), "rmsprop", lr=2.5e-4).defaults["alpha"]
        0.99
    """
    if name not in OPTIMIZERS:
        raise ValueError(f"Invalid optimiser name={name!r}: one of {OPTIMIZERS}")
    if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not lr > 0:
        raise ValueError(f"Invalid lr={lr!r}: a number > 0")
    if fused is not None and not isinstance(fused, bool):
        raise ValueError(f"Invalid fused={fused!r}: true, false or null (auto)")
    params = list(params)
    if name == "rmsprop":
        if fused:
            raise ValueError("Invalid fused=True with name='rmsprop': PyTorch's RMSprop has "
                             "no fused kernel (use fused=None or False)")
        return torch.optim.RMSprop(params, lr=lr, eps=eps, alpha=alpha)
    if fused is False:
        return torch.optim.Adam(params, lr=lr, eps=eps)
    can = fused_supported(params)
    if fused and not can:
        kinds = sorted({f"{p.dtype} on {p.device.type}" for p in params}) or ["no parameters"]
        raise ValueError(f"Invalid fused=True: Adam's fused kernel does not take these "
                         f"parameters ({', '.join(kinds)}); use fused=None or False")
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True if can else None)
