"""What leaves a process as bytes: saved files holding tensors and plain data only (`files`) and
the one policy file format (`policy_file`)."""
