"""A ROS 2 robot as a body: rmw_zenoh's wire format and the competencies over it."""
