"""The offline RL methods a recipe can name: the networks (``networks``, ``bcq_networks``), the IQL, CQL, BC
and BCQ losses with the paper's weight decay (``iql``, ``bcq``, ``losses``), the ``Method`` the trainer
trains (``method``) and the registry that builds one from the recipe sections it reads (``registry``, ``config``).

The run machinery above them (recipes, trainer, evaluation, policies) is :mod:`rm_torchrl.train`; nothing
here imports it.
"""
