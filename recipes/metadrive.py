"""REINFORCE on MetaDrive, offline and headless (the metadrive extra; docs/recipes/metadrive.md).

In a checkout, `python recipes/metadrive.py [FLAGS]` is `rl-pg train metadrive [FLAGS]`;
the recipe itself is rl_pg/recipes/metadrive.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
