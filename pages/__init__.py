"""The results pages: a capture run's page, a dataset's page, the store's copies of them and
the links that open them, and the server of those links for a store in a folder. Imported by
the flows and the command line; they import the tasks and the science only. Installed as
``facecap.pages``."""
