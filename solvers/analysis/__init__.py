"""What is the rigid model getting wrong: the causes (effects/), candidate search, scoring and naming."""
