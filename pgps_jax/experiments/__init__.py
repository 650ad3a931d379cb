"""Experiments of the paper beyond single training runs: `paper` (Section 5: Figures 4-6,
Table 1) and `landscape` (Appendix A)."""
