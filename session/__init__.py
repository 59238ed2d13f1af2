"""The session core: from a session config to the steps of a session, with no I/O.

One place builds a session's world, learner and random streams from its config and steps
it: the live service, the re-run and resume of a recording, the offline simulation, the
benches and the memory probe all drive a `session.core.Session`.
"""
