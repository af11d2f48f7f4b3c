"""Prefect tasks: thin, cached, retried wrappers of facecap_core calls over the artifact store.
Installed as ``facecap.tasks``."""
