"""What the weather is, before any pair is seen: presets (:mod:`.presets`, grouped in
:mod:`.preset_groups`), the billboard templates that give particles their shape (:mod:`.templates`),
the atmosphere model (:mod:`.atmosphere`) and a field's optics (:mod:`.optics`)."""
