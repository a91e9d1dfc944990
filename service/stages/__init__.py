"""The stages of ``Registrar.register``, one module each, in the order they run:

validate (:mod:`.validate`) -> anchor (:mod:`.anchor`: each cloud about its own centroid) -> sample
(:mod:`.sample`) -> normalise (:mod:`.normalise`) -> network
(:mod:`.network`) or rotation search (:mod:`.search`) -> refine (:mod:`.refine`: candidate ranking in
:mod:`.ranking`, multistart in :mod:`service.multistart`) -> slide check (:mod:`.slide`) -> after a search, flip
check (:mod:`.flip`) -> assess (:mod:`.assess`); ``rotation_search="auto"``
solves again with the search when the plain result looks wrong (:func:`.search.auto_search`); last, the fine
refinement (:mod:`.fine`) of the result kept, its free-space check where a cloud is a range image
(:mod:`.free_space`), the symmetry check of a ``reliable`` one (:mod:`.symmetry`), and its pose back in the
caller's frames.
After the anchor stage every stage works on the anchored clouds: where a stage says "the caller's frame" or "the
caller's units", it means the caller's units in frames moved to each cloud's centroid; only ``Registrar.register``'s
result is back in the caller's own frames.
:class:`.pipeline.Stages` names the functions a :class:`service.registrar.Registrar` calls, so that one can be
replaced or wrapped without touching the others.
"""
