"""Experiments of the paper beyond training runs (`landscape`: Appendix A)."""
