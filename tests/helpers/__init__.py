"""Helpers shared by test modules (rigs, payloads, device contracts); no tests here."""
