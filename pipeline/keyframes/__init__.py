"""keyframes: task config, keyframe selection, f_edit (D_edit) / rule editing (D_rule), terrain, figure.

Public names are loaded on first use so that importing `pipeline.keyframes.tracking_data` stays light.
"""

_EXPORTS = {
    "TaskConfig": "config", "load_tasks": "config", "load_yaml_strict": "config",
    "KeyframeTable": "select", "select_keyframes": "select", "detect_foot_contacts": "select",
    "find_flights": "select", "task_flights": "select",
    "build_tracking_data": "edit", "sample_psi": "edit", "apply_offsets": "edit",
    "write_tracking_dataset": "datasets", "load_tracking_data": "datasets",
    "terrain_builder": "terrain", "terrain_layout": "terrain", "apply_layout": "terrain",
    "keyframe_figure": "figure", "rule_video": "rule_video", "build_task_outputs": "outputs",
    "TrackingData": "tracking_data",
}


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(name)
