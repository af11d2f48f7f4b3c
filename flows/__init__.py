"""Prefect flows of facecap: a capture, a dataset, the nightly evaluation; the links to their
pages (:mod:`facecap.pages`) from the UI. Installed as ``facecap.flows``."""
