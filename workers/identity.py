"""What a dask worker must share with the process that sends it tiles.

:func:`identity` runs on every worker of an external cluster (``Client.run``) and in
the submitting process; :func:`workers.cluster.check_workers` compares the answers.
This module imports nothing of the project at module level: a worker lacking the
project fails to load it at all (the answer is then the import error), and a worker
lacking one of its dependencies answers with the module it could not import.
"""

from __future__ import annotations

#: The distribution that holds ``pipeline``, ``workers`` and ``service``.
DISTRIBUTION = "orchard-trees"


def identity() -> dict:
    """This interpreter's view of the project.

    Returns
    -------
    dict
        ``host`` and ``python`` (the executable) say where; then either ``error`` (the
        project, or a module it needs, cannot be imported: ``"ModuleNotFoundError: No
        module named 'laspy'"``), or ``version`` (of :data:`DISTRIBUTION`; None when
        the code is on the path without being installed) and ``schema`` (a short
        SHA-256 of the pipeline parameters' JSON schema: two revisions that read the
        same job parameters differently differ here even under one version number).
    """
    import hashlib
    import json
    import platform
    import sys
    from importlib import metadata

    answer: dict = {"host": platform.node(), "python": sys.executable}
    try:
        import workers.tasks  # noqa: F401 - the tasks' module, and everything it imports
        from pipeline.params import PipelineParams
    except Exception as exc:  # noqa: BLE001 - any failure to load is the answer
        answer["error"] = f"{type(exc).__name__}: {exc}"
        return answer
    try:
        answer["version"] = metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        answer["version"] = None
    schema = json.dumps(PipelineParams.model_json_schema(), sort_keys=True)
    answer["schema"] = hashlib.sha256(schema.encode()).hexdigest()[:16]
    return answer
