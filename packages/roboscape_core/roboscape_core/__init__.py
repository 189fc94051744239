"""What the pipeline and the policy plugins share without the simulator stack: the errors a user can fix, and the
contract PPO reads from a policy."""
