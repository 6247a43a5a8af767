"""Ours in one place: the paper's method is IQL on the RM-refined data, with the settings chosen here.

Ours (*Less Is More*, section 4) trains IQL (Kostrikov et al. 2021) on the data the event-ordered reward machine
refines (``data.refine: paper``); the actor, twin critics and value network read the state with its RM
encoding, (s, u). For a batch of transitions (s, u, a, r, s', u', d):

.. code-block:: text

    L_V(psi)   = E[ L2_tau( min_i Qbar_i(s, u, a) - V_psi(s, u) ) ]          L2_tau(x) = |tau - 1(x < 0)| x^2
    L_Q(theta) = E[ sum_i (r + gamma (1 - d) V_psi(s', u') - Q_theta_i(s, u, a))^2 ] + lambda_Q ||theta||^2  (eq. 7)
    L_pi(phi)  = -E[ min(exp(beta (min_i Qbar_i(s, u, a) - V_psi(s, u))), 100) log pi_phi(a | s, u) ]
                 + lambda_pi ||phi||^2                                                                    (eq. 8)

Qbar are the target critics, Polyak-averaged at rate 0.005. The penalty lambda ||w||^2 has the gradient
2 lambda w, so Adam's coupled ``weight_decay`` is 2 lambda (``optim.decay: l2``, :func:`~rm_torchrl.methods.optim.adam`);
lambda_Q applies to the value network too. The actor's rate is cosine-annealed to 0 over the run, as IQL's authors
do. The losses are :class:`~rm_torchrl.methods.iql.SharedForwardIQLLoss` (TorchRL's ``IQLLoss``).

Values. Every setting not listed is IQL's published one (``recipes/method/iql.yaml``: networks 256-256, batch 256,
gamma 0.99, Adam 3e-4 for the critics, actor dropout 0.1, the Gaussian actor). Each listed one was chosen by
looking at evaluations, as recorded in ``benchmarks/results/choices.json`` (rules: ``benchmarks/PROTOCOL.md``):

================================  ===========  ===============================================================
setting (recipe key)              value        where it came from
================================  ===========  ===============================================================
expectile tau                     0.9          IQL's AntMaze value (a 0/-1 step reward, as the RM's); kept by
(``method.iql.expectile``)                     the decline study, door-human-v0 seeds 0-2 at 50k
inverse temperature beta          10           IQL's AntMaze value; kept by the same study
(``method.iql.temperature``)
beta on kitchen, door-cloned,     0.5          temperature studies on the generated stand-ins (kitchen-partial
relocate (:data:`TEMPERATURE_OF`)              seeds 0-1, door-cloned 0-1, relocate-human 0-1, relocate-cloned 0)
lambda_Q, lambda_pi               1e-3         the paper gives none: highest mean of the last five evaluations
(``optim.weight_decay_q/_pi``)                 among 0, 1e-4, 1e-3, 1e-2 (decline study, seeds 0-2)
actor rate                        3e-4 x       IQL's 3e-4 up to 50k updates, then 3e-4 x 50k / steps (3e-5 at
(``optim.lr_actor``)              min(1, 50k   500k): the actor memorised its refined transitions at 500k with
                                  / steps)     3e-4 (door-human-v0 500k study, seed 0)
================================  ===========  ===============================================================

The recipe option ``method=ours`` (``recipes/method/ours.yaml``) is written from :data:`OURS` by
``python -m rm_torchrl.methods.ours``; a test keeps the two equal. A dataset option of your own may set
``tuned.ours.temperature``, which wins over :data:`TEMPERATURE_OF`.

References: Kostrikov, Nair and Levine, *Offline Reinforcement Learning with Implicit Q-Learning*, ICLR 2022;
the paper in ``../shared/paper/less-is-more-reward-machines.md``.

    >>> OURS.expectile, OURS.weight_decay_q, temperature_for("rmrl-kitchen-partial"), temperature_for("door-human-v0")
    (0.9, 0.001, 0.5, 10.0)
"""
from __future__ import annotations

from dataclasses import dataclass, field

import yaml

#: data.name -> ours' inverse temperature where a temperature study chose one; a generated stand-in
#: (``rmrl-NAME``) takes NAME's, since the studies ran on the stand-ins and D4RL's files inherit their value
TEMPERATURE_OF = {"kitchen-partial": 0.5, "kitchen-mixed": 0.5, "kitchen-complete-v0": 0.5, "door-cloned": 0.5,
                  "relocate-human": 0.5, "relocate-cloned": 0.5}


@dataclass(frozen=True)
class OursSettings:
    """Ours' own values (the module docstring says where each came from)."""

    expectile: float = 0.9
    temperature: float = 10.0
    temperature_of: dict = field(default_factory=lambda: dict(TEMPERATURE_OF))
    weight_decay_q: float = 1e-3
    weight_decay_pi: float = 1e-3
    lr_actor: str = "3.0e-4"  # as the recipe spells it: the rate up to lr_actor_reference_steps
    lr_actor_reference_steps: int = 50_000


OURS = OursSettings()


def temperature_for(dataset: str) -> float:
    """Ours' inverse temperature on ``data.name`` (the ``${ours_temperature:${data.name}}`` resolver)."""
    name = str(dataset)
    return float(OURS.temperature_of.get(name.removeprefix("rmrl-"), OURS.temperature))


def option(settings: OursSettings = OURS) -> dict:
    """The ``method=ours`` recipe option: the iql option with ours' settings, on the refined data."""
    return {
        "defaults": ["iql", "_self_"],
        "data": {"refine": "paper"},
        "method": {"hparams": "ours", "iql": {
            "expectile": settings.expectile,
            "temperature": "${oc.select:tuned.ours.temperature,${ours_temperature:${data.name}}}"}},
        "optim": {"lr_actor": f"${{scaled_to_budget:{settings.lr_actor},{settings.lr_actor_reference_steps},"
                              "${trainer.steps}}",
                  "weight_decay_q": settings.weight_decay_q, "weight_decay_pi": settings.weight_decay_pi},
    }


HEADER = ("# @package _global_\n"
          "# ours: the paper's method as a preset: IQL with ours' settings (method.hparams: ours) on the refined data\n"
          "# (data.refine: paper); data.refine=none gives IQL with ours' settings on the raw data.\n"
          "# Written by `python -m rm_torchrl.methods.ours` from rm_torchrl/methods/ours.py, which says where each\n"
          "# value came from: edit that, not this file.\n")


def option_yaml(settings: OursSettings = OURS) -> str:
    """``recipes/method/ours.yaml`` as :func:`option` makes it."""
    return HEADER + yaml.safe_dump(option(settings), sort_keys=False, default_flow_style=None, width=120)


if __name__ == "__main__":
    print(option_yaml(), end="")
