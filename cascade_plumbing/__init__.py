"""What the training scripts share and is not the algorithm (the CleanRL `cleanrl_utils` idea).

Each script at the top level of the repository defines its own method: `Args`, the nets, the loss,
the training loop and what is evaluated. Everything else lives here, once:

- `errors`: the one-line error (`fail`), the ranges of the real-valued settings (`check_ranges`);
- `processes`: worker and run processes in process groups of their own that end with their parent;
- `envs`: env construction, the wrappers that save and restore an env's state, training videos;
- `tracking`: Weights & Biases (`--track`), the progress line;
- `checkpoints`: atomic checkpoint files, their repair and loading;
- `evaluation`: the worker process that runs evaluations beside training, the envs of evaluation episodes,
  the start of --evaluate;
- `runs`: seeding and RNG state, run names, resume, stop signals, the command-line entry point;
- `replay`: the replay buffer of the off-policy scripts;
- `offpolicy`: the rest the off-policy scripts (SAC, DDPG) share: their common input checks, evaluation
  episodes, --evaluate of a saved model, and a run's bookkeeping around the training loop;
- `discrete`: what the two discrete-action scripts share: the discretization of a Box action space (the paper's
  Appendix I), their env stacks and checks, their run folder, their evaluation episodes;
- `ppo`: what the continuous PPO scripts share: CleanRL's env stack, the checks of their settings, CleanRL's
  update scalars;
- `fast`: optimizer and check helpers of the scripts' fast paths (the paths themselves stay in the scripts,
  next to the definitions they are checked against).

A copy of a script in the repository root imports this package as is; a copy elsewhere needs
`pip install -e <repository>` once.
"""
