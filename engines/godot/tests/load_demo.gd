extends SceneTree
# The demo scene loads and builds (tests/test_godot.py): its scripts parse and its nodes are there.


func _initialize():
	var scene = load("res://demo.tscn")
	var ok: bool = scene != null
	if ok:
		var demo = scene.instance()
		demo.get_node("AvatarMotorClient").auto_open = false
		root.add_child(demo)
		ok = demo.has_method("_on_frame") and demo.get_node("AvatarMotorClient").has_method("spawn") and demo.get_node("Camera") is Camera
	print("DEMO " + ("ok" if ok else "broken"))
	quit(0 if ok else 1)
