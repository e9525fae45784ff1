"""REINFORCE on CartPole-v1 until greedy play is solved (mean >= 475 over 20 episodes).

In a checkout, `python recipes/cartpole.py [FLAGS]` is `rl-pg train cartpole [FLAGS]`;
the recipe itself is rl_pg/recipes/cartpole.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
