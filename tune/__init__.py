"""From model.yaml to controller.yaml: scenarios x sampled plants, objective, Optuna study."""
