"""Synthetic RGB-D scenes with a stand-in body, bag tools, closed-loop simulator and evaluation."""
