"""The browser view (``cfbci view``): its server, its model of the sessions, its pages."""
