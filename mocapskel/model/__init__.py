"""What a skeleton is: its tree, its kinematics, its humanoid names, and the small measures the stages share.

The model imports nothing of the package but itself, the artifacts and the errors (see ARCHITECTURE.md).
"""
