"""The browser view (``cfbci view``): its server, its model of the sessions, its pages."""

#: The environment variable that gives the view its access token (else ``--token``, else a
#: random one).
TOKEN_ENV = "CFBCI_VIEW_TOKEN"
