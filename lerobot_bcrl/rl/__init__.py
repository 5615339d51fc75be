"""BC+RL fine-tuning: PPO with a decaying behavioural-cloning term (docs/method.md section 4), `bcrl-finetune`.

`ppo.py` holds the algorithm and the loop; `configuration.py` the command line, `cli.py` the entry point,
`build.py`, `rollout.py`, `schedule.py`, `demo_buffer.py`, `checkpoint.py` and `logger.py` one part each.
"""
