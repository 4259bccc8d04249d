"""Robustness: the perturbation table, a stored cell rescored on perturbed held-out windows
(rescore), the session's robustness cases (cases), and perturbed closed-loop rollouts
(closed_loop). Its records are bench.results.robust's."""
