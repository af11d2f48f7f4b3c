"""facecap: one handheld video or photo set of a still face to a metric, topologically
consistent 3D face mesh, at dataset scale.

The installed package holds the command line (``facecap.cli``) above the Prefect flows
(``facecap.flows``), their deployments (``facecap.deploy``) and the tasks over the artifact
store (``facecap.tasks``); the science is ``facecap_core``. Layers import downwards only:
cli → deploy → flows → tasks → facecap_core.
"""
