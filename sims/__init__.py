"""Simulated tasks for wfnn: pure numpy boat, cart-pole and 1-DOF positioning (thesis Ch 3-4, App A)."""
