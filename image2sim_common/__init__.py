"""What every image2sim package uses, below all three of them: output folders that appear whole or not at all and
the registry of the records that mark them (`outdir`), rotations and frames (`rotations`), the progress-callback
type (`progress`) and the headless-GL set-up (`headless_gl`). It imports none of `reconstruction`, `scene_export` or
`grounder`, and nothing heavier than numpy.
"""

__all__ = ["headless_gl", "lazy", "outdir", "progress", "rotations"]
