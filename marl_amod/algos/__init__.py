"""Training algorithms, one readable file each (online :mod:`.a2c`, :mod:`.sac`; offline :mod:`.bc`,
:mod:`.iql`, :mod:`.cql`), the plumbing they share (:mod:`.common`, :mod:`.rollout`, :mod:`.offline`)
and the registry the CLI reads (:mod:`.registry`: ``ALGOS``).

Nothing is imported here, so ``import marl_amod.algos.common`` never loads an algorithm and the
algorithms never import the package that lists them.
"""
