"""The offline RL methods a recipe can name, and the recipe sections they read (:mod:`rm_torchrl.methods.config`)."""
