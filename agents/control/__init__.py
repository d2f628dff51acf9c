"""Follower controllers: the paper's tracking (eq. 1-3) and ICR (eq. 7) laws, and ours."""
