"""HMRTA coordinator: task_board, sim_robot and the mission launcher."""
