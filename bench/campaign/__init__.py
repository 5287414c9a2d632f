"""Monte Carlo campaigns: many dispersed landings, run in parallel and summarised."""
