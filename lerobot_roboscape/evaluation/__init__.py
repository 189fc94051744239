"""Success rates of policies in the ManiSkill simulator (IND and OOD scenes) and the paper's tables."""
