"""``python -m marl_amod``: the ``marl-amod`` command, for a checkout used without installing its entry point."""

from marl_amod.cli import main

main()
