"""Where a pair's particles come from: the paper's model, visible particles drawn for one pair
(:mod:`.pair`); a weather field in the world, seen by every camera (:mod:`.field`); the paper's
published weather files (:mod:`.published`); and the memory a draw takes, checked first
(:mod:`.budget`)."""
