import torch

# The test networks are tiny: one thread is as fast and stays fast when other jobs load the machine.
torch.set_num_threads(1)
