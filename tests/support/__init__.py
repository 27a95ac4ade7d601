"""Test support: fakes of the device contracts and helpers shared by the tests."""
