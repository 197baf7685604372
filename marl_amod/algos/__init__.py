"""Training algorithms, one readable file each (:mod:`.a2c`, :mod:`.sac`), the plumbing they share
(:mod:`.common`, :mod:`.rollout`) and the registry the CLI reads (:mod:`.registry`: ``ALGOS``).

Nothing is imported here, so ``import marl_amod.algos.common`` never loads an algorithm and the
algorithms never import the package that lists them.
"""
