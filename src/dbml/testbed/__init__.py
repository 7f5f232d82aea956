"""Testbeds: real, shaped networks on one machine for experiments and integration tests."""

from dbml.testbed.netns import Host, Network, TestbedError, leftover_namespaces, privilege_problem

__all__ = ["Host", "Network", "TestbedError", "leftover_namespaces", "privilege_problem"]
