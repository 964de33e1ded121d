"""Graph files: every shipped deployment validates, and each kind of broken graph is refused by node and field."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import run_cli

from mocapflow.errors import GraphError
from mocapflow.runtime.graph import load_graph, validate

DEPLOYMENTS = sorted((Path(__file__).resolve().parents[1] / "deployments").glob("*.yaml"))

GOOD = """
name: t
nodes:
  tracker: {plugin: simulator, config: {rig: human, rate: 120}}
  recorder: {plugin: recorder, inputs: {markers: tracker/markers}, config: {path: out.c3d}}
"""


@pytest.mark.parametrize("path", DEPLOYMENTS, ids=lambda p: p.name)
def test_shipped_deployments_validate(path: Path) -> None:
    graph = load_graph(path)
    assert graph.nodes


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    return path


def test_good_graph_and_overrides(tmp_path: Path) -> None:
    graph = load_graph(write(tmp_path, GOOD), ["tracker.rate=480", "recorder.path=x/y.c3d", "tracker.unlabelled=true"])
    assert graph.nodes["tracker"].config == {"rig": "human", "rate": 480, "unlabelled": True}
    assert graph.nodes["recorder"].config["path"] == "x/y.c3d"
    assert graph.key_prefix == "mocapflow/t"


@pytest.mark.parametrize(
    "text, expected",
    [
        ("name: t\nnodes:\n  a: {plugin: simulator\n", r"graph.yaml:\d+:\d+: YAML syntax error"),
        ("name: t\nnodes:\n  a: [1, 2\n  b: 3\n", r"YAML syntax error"),
        ("- just\n- a list\n", r"must be a mapping"),
        ("name: t\nnodes: {}\n", r"nodes: .*at least one node"),
        ("name: t\nnodes:\n  _x: {plugin: simulator}\n", r"node name '_x'"),
        ("name: t\nnodes:\n  a: {plugin: simulator, colour: red}\n", r"nodes.a.colour: Extra inputs"),
        (GOOD.replace("plugin: simulator", "plugin: teleporter"), r"nodes.tracker.plugin: unknown plugin 'teleporter'"),
        (GOOD.replace("rate: 120", "rate: -5"), r"nodes.tracker.config.rate: Input should be greater than 0"),
        (GOOD.replace("rate: 120", "rate: 120, colour: red"), r"nodes.tracker.config.colour: Extra inputs"),
        (GOOD.replace("path: out.c3d", "path: out.txt"), r"nodes.recorder.config.path: .*\.c3d or \.trc"),
        (GOOD.replace("{markers: tracker/markers}", "{}"),
         r"nodes.recorder.inputs.markers: required input is not linked"),
        (GOOD.replace("{markers: tracker/markers}", "{markers: tracker/markers, gps: tracker/markers}"),
         r"nodes.recorder.inputs.gps: plugin 'recorder' has no input 'gps'"),
        (GOOD.replace("tracker/markers}", "camera/markers}"),
         r"nodes.recorder.inputs.markers: 'camera/markers' must be"),
        (GOOD.replace("tracker/markers}", "tracker/points}"),
         r"nodes.recorder.inputs.markers: node 'tracker' has no output 'points'"),
        (GOOD.replace("tracker/markers}", "tracker/truth}"),
         r"nodes.recorder.inputs.markers: type mismatch: tracker/truth carries SimTruth, input expects MarkerFrame"),
    ],
    ids=["yaml-unclosed", "yaml-bad-flow", "not-mapping", "no-nodes", "bad-name", "unknown-node-field",
         "unknown-plugin", "bad-config-value", "unknown-config-field", "bad-path", "missing-input", "unknown-input",
         "unknown-node", "unknown-output", "type-mismatch"],
)
def test_broken_graphs_are_refused_by_node_and_field(tmp_path: Path, text: str, expected: str) -> None:
    with pytest.raises(GraphError, match=expected):
        load_graph(write(tmp_path, text))


def test_all_errors_are_reported_at_once(tmp_path: Path) -> None:
    text = GOOD.replace("rate: 120", "rate: -5").replace("tracker/markers}", "tracker/truth}")
    with pytest.raises(GraphError) as info:
        load_graph(write(tmp_path, text))
    assert "nodes.tracker.config.rate" in str(info.value) and "nodes.recorder.inputs.markers" in str(info.value)


def test_bad_override(tmp_path: Path) -> None:
    with pytest.raises(GraphError, match="no node 'ghost'"):
        load_graph(write(tmp_path, GOOD), ["ghost.rate=1"])
    with pytest.raises(GraphError, match="expected NODE.KEY=VALUE"):
        load_graph(write(tmp_path, GOOD), ["tracker"])


@pytest.mark.integration
def test_validate_command_exit_codes(tmp_path: Path) -> None:
    good = run_cli("validate", write(tmp_path, GOOD))
    assert good.returncode == 0 and "ok (2 nodes" in good.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text(GOOD.replace("rate: 120", "rate: fast"))
    result = run_cli("validate", bad)
    assert result.returncode == 2
    assert "nodes.tracker.config.rate" in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_node_health_links_only_to_the_stats_of_this_graph(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    head = "name: h\nnodes:\n  tracker: {plugin: simulator}\n"
    sink = "  view: {plugin: rerun, config: {save: s.rrd}, inputs: {markers: tracker/markers, health: %s}}\n"
    for link in ("_stats/*", "_stats/tracker"):
        path.write_text(head + sink % link)
        load_graph(path)
    for link in ("_stats/nobody", "tracker/markers"):
        path.write_text(head + sink % link)
        with pytest.raises(GraphError, match=rf"nodes.view.inputs.health: node health is linked as '_stats/\*' "
                                             rf"\(every node\) or '_stats/NODE' .*, not '{link}'"):
            load_graph(path)
    path.write_text(head + "  view: {plugin: rerun, config: {save: s.rrd}, inputs: {markers: _stats/*}}\n")
    with pytest.raises(GraphError, match="nodes.view.inputs.markers: '_stats/\\*' carries NodeStats, input expects "
                                         "MarkerFrame"):
        load_graph(path)


def test_an_output_read_only_through_its_copies_is_not_sent_for_other_processes(tmp_path: Path) -> None:
    """The quickstart's model stages read the filled markers' sampled copy: the frame group need not send the whole
    stream for them (only while someone subscribes), but sends the models they send back; a model stage that reads
    the whole stream (``queue: all``) has it sent."""
    path = DEPLOYMENTS[0].with_name("quickstart.yaml")
    graph = load_graph(path)
    classes = validate(graph)
    assert graph.linked_outputs("filler", classes) == []
    assert graph.linked_outputs("clusterer", classes) == ["segments"]
    assert graph.linked_outputs("joints", classes) == ["skeleton"]
    raw = yaml.safe_load(path.read_text())
    raw["nodes"]["clusterer"]["queue"] = {"markers": "all"}
    graph = load_graph(write(tmp_path, yaml.safe_dump(raw)))
    assert graph.linked_outputs("filler", validate(graph)) == ["markers"]
