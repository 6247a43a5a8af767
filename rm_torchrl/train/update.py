"""One gradient update of a method, stopped before any optimiser step applies a NaN or inf, and the first one,
in which ``torch.compile`` compiles."""
from __future__ import annotations

import sys
import time

import torch
from tqdm import tqdm


class NonFinite(RuntimeError):
    """A loss term or gradient became NaN or inf: the run cannot continue meaningfully."""


def check_gradients(method) -> None:
    params = [p for opt in method.optimizers for g in opt.param_groups for p in g["params"] if p.grad is not None]
    norms = torch._foreach_norm([p.grad for p in params])
    if not bool(torch.isfinite(torch.stack(norms)).all()):
        names = {id(p): n for n, p in method.loss.named_parameters()}
        bad = next(p for p, n in zip(params, norms) if not torch.isfinite(n))
        raise NonFinite(f"the gradient of {names.get(id(bad), 'a parameter')}")


def gradient_step(method, terms, batch):
    """One update of every network of ``method`` on ``batch``; returns the loss TensorDict.

    Raises :class:`NonFinite` naming the term (or parameter) as soon as a loss term or a gradient
    is NaN or inf, before any optimiser step applies it.
    """
    losses = method.compute_loss(batch)
    total = sum(losses.get(t) for t in terms)
    if not bool(torch.isfinite(total)):
        raise NonFinite(next((t for t in terms if not bool(torch.isfinite(losses.get(t)))), "the total loss"))
    for opt in method.optimizers:
        opt.zero_grad(set_to_none=True)
    total.backward()
    check_gradients(method)
    for opt in method.optimizers:
        opt.step()
    if method.target_updater is not None:
        method.target_updater.step()
    return losses


def first_step(method, terms, batch):
    """The first update, in which ``torch.compile`` compiles (saying so: it takes a while before the
    first step shows); if compiling fails, say so and train eagerly."""
    if method.compiled is None:
        return gradient_step(method, terms, batch)
    tqdm.write("compiling the update with torch.compile (first step; about a minute on CPU) ...", file=sys.stderr)
    started = time.perf_counter()
    try:
        losses = gradient_step(method, terms, batch)
    except NonFinite:
        raise
    except Exception as err:  # e.g. no C++ compiler: eager training is slower, not different; real errors recur
        method.compiled = None
        tqdm.write(f"warning: torch.compile failed ({type(err).__name__}: {str(err).splitlines()[0][:200]}); "
                   "training without it (set trainer.compile=false to skip the attempt)", file=sys.stderr)
        return gradient_step(method, terms, batch)
    tqdm.write(f"compiled in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return losses
