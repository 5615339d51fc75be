"""BC+RL fine-tuning: PPO with a decaying behavioural-cloning term (method.md section 4).

`schedule.py` gives theta_t, `rollout.py` the env workers, `ppo.py` the algorithm and the `bcrl-finetune` CLI.
"""
