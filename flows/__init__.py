"""Prefect flows of facecap and the ``facecap`` command line that starts them."""
