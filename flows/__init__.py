"""Prefect flows of facecap: a capture, a dataset, the nightly evaluation; their pages and
the links to them from the UI. Installed as ``facecap.flows``."""
