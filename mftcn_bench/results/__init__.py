"""Results: the store, JSON records, which runs count, statistics over seeds, leaderboards, the paper's
tables and plots."""
