"""Small shared helpers every layer may import: argument checks, strict JSON, keyed random numbers,
optional extras, thread limits, quaternion maths. Nothing here imports another layer."""
