"""Masters (command sources) and slaves (executors) that attach to a robot."""
