"""Training the frontend: losses (paper eq. 8-11, App. D.2), the three-stage curriculum (App. D.3), the trainer."""
