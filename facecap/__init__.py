"""facecap: one handheld video or photo set of a still face to a metric, topologically
consistent 3D face mesh, at dataset scale.

The installed package holds the command line (``facecap.cli``) above the Prefect flows
(``facecap.flows``), their deployments (``facecap.deploy``), the results pages
(``facecap.pages``) and the tasks over the artifact store (``facecap.tasks``); the science is
``facecap_core``. Layers import downwards only: cli → deploy → flows → pages → tasks →
facecap_core.
"""

from pathlib import Path

# In a checkout the flows, pages, tasks and deployments are the repository's top-level folders
# (where Prefect's entrypoints and the compose stack find them), which the install places
# inside this package. Where this package is the checkout's folder (the working directory of
# a worker or of a command run in the repository comes first on sys.path) they are found
# beside it, whether facecap was installed from it, installed as a copy, or not at all.
_CHECKOUT = Path(__file__).resolve().parent.parent
if not (Path(__file__).parent / "flows").is_dir() and (_CHECKOUT / "flows" / "__init__.py").is_file():
    __path__.append(str(_CHECKOUT))
