import torch as th

# The suite's networks and batches are tiny: one thread avoids oversubscribing CI's two cores
th.set_num_threads(1)
