"""The runtime the node processes share: broker and topics, the node base class, parameters,
the launcher, driver back-ends, introspection and the test helpers.
"""
