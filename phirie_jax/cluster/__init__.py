"""Many scenes at once on Ray (``phirie convert-many``; the ``cluster`` extra).

``driver``: names the scenes, checks the output folders, connects to Ray, submits one task per
scene, retries and records, writes ``ROOT/summary.json``. ``scene_task``: one scene's conversion
in a worker process and the record it returns. ``table``: the terminal's view of the records.
Ray is imported by the driver only, when the command runs.
"""


class ScenesFailed(RuntimeError):
    """Some scenes of ``phirie convert-many`` failed (each recorded with its reason in
    ``ROOT/summary.json``); the others were converted. The CLI prints this one line, exits 1."""
