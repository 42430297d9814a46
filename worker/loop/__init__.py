"""Loop closure: bag of hidden states, loop detection, relocalization (hidden state or PnP) and the Sim(3) pose graph.

Submodules are imported directly (`from worker.loop.pose_graph import Sim3PoseGraph`) so that importing the
package stays light (OpenCV and GTSAM load only where used).
"""
