"""The robot core: model, safety state machine, motion limits, the actor and its manager."""
