"""``python -m marl_amod``: the ``marl-amod`` command, for a checkout used without installing its entry point."""

from marl_amod.cli import main

if __name__ == "__main__":  # importing the module (docs tools, the docs-name test) runs no command
    main()
