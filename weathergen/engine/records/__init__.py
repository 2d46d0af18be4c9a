"""The particle records that sampling makes and rendering reads: one weather's :class:`Particles`
(:mod:`.particles`), a combined preset's layers (:mod:`.layered`) and the render settings that
travel with a record (:mod:`.settings`)."""
