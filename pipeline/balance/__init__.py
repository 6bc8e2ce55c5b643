"""The balance policy: the G1 standing in its stance, brought back there after pushes and landings.

A task's chain runs stand (balance) → go → task → balance: `config` (params.yaml `balance:`), `starts`
(the task policies' own end states as training starts), `train` (PPO on `envs.balance_env`) and
`export` (ONNX + policy.json + hub format, like every policy).
"""
