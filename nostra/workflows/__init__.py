"""Workflows that combine the parts (data, models, policies, sim): training and its rollouts,
evaluation and offline analysis, reports, tracking, DDP. Nothing below nostra/ imports them."""
